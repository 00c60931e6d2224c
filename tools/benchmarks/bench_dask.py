"""Pairs per second of the Dask path against the one-process batch, and one
huge image's row tiles on 1 and 2 workers, A/B in one run (KITTI 2015 frames
from $MCCNN_DATA, default ../shared/data beside the repository).

    python tools/benchmarks/bench_dask.py                       # 8 KITTI 2015 pairs, kitti-fst, D = 228
    python tools/benchmarks/bench_dask.py --cost census --pairs 6 --rounds 2
    python tools/benchmarks/bench_dask.py --huge-only
    python tools/benchmarks/bench_dask.py --overhead-only      # fixed cost per pair: 40 tiny pairs

Pairs: the one-process batch (one StereoMatcher, as ``mccnn-cl match -l -r``)
beside :func:`mccnn_cl.distributed.match_pairs` on a LocalCluster of 1 and of
2 worker processes (1 thread each).  Each cluster is started and warmed
(every worker builds its matcher) before the clock starts, and the
one-process matcher is warmed on the first pair; the start-up times are
printed apart.  The Dask path's overhead per pair is (1-worker time -
one-process time) / pairs.  ``--rounds`` repeats the three in turn (best
kept), so the machine's load hits all of them alike.

Huge image: a 2 x 2 mosaic of four KITTI frames (2484 x 750) with census,
D = 128 and a memory limit that makes row tiles: the one-process tiled run
(:meth:`StereoMatcher.compute`) beside its tiles split over 1 and 2 workers
(``split_tiles=True``); the maps are checked equal.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time

import numpy as np

from _paths import data_dir  # noqa: E402
#: the shared data: $MCCNN_DATA, default ../shared/data beside the repository root
DATA = data_dir()
SHARED = DATA / "kitti2015" / "training"
FRAMES = ("000000", "000001", "e00001", "e00002", "e00003", "e00004", "e00006", "e00007", "e00008", "e00010")


def cpu_name():
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def one_process(jobs, args):
    from mccnn_cl.batch import compute_pair
    from mccnn_cl.pipeline import StereoMatcher
    kw = dict(cost=args.cost, max_disparity=args.max_disp)
    if args.cost == "cnn":
        kw["weights"] = args.weights
    m = StereoMatcher(**kw)
    compute_pair(jobs[0], lambda d: m, args.max_disp, False)  # warm: kernels built, volumes kept
    t = time.perf_counter()
    outs = [compute_pair(j, lambda d: m, args.max_disp, False).disparity for j in jobs]
    return time.perf_counter() - t, outs


def on_cluster(jobs, args, workers):
    from distributed import Client

    from mccnn_cl import distributed as dd
    config = dd.matcher_config(cost=args.cost, weights=args.weights if args.cost == "cnn" else None)
    t0 = time.perf_counter()
    with dd.local_cluster(workers) as cluster, Client(cluster) as client:
        client.run(dd.warm, config, args.max_disp)
        # one pair per worker first: kept volumes exist (as the one-process matcher's warm-up)
        list(dd.match_pairs(client, jobs[:workers], config, args.max_disp, split_tiles=False))
        start = time.perf_counter() - t0
        t = time.perf_counter()
        res = {j.name: r for j, r in dd.match_pairs(client, jobs, config, args.max_disp, split_tiles=False)}
        return time.perf_counter() - t, [res[j.name].disparity for j in jobs], start


def overhead(args, tmp):
    """Fixed cost per pair of the Dask path: 40 tiny pairs (64 x 48 crops, census,
    D = 8), whose matching takes a few ms, one process beside 1 worker."""
    from mccnn_cl.batch import Job
    from mccnn_cl.io import read_image, write_image
    jobs = []
    for i in range(40):
        f = FRAMES[i % len(FRAMES)]
        paths = []
        for side in ("image_2", "image_3"):
            p = os.path.join(tmp, f"tiny_{side}_{i}.png")
            y, x = 100 + 4 * i, 300 + 10 * i
            write_image(p, read_image(SHARED / side / f"{f}_10.png")[y:y + 48, x:x + 64])
            paths.append(p)
        jobs.append(Job(f"tiny{i}", paths[0], paths[1], os.path.join(tmp, f"tiny{i}.pfm")))
    a = argparse.Namespace(cost="census", weights=None, max_disp=8)
    best = {}
    for _ in range(args.rounds):
        t, ref = one_process(jobs, a)
        best["one"] = min(best.get("one", 1e9), t)
        t, outs, _ = on_cluster(jobs, a, 1)
        best["dask"] = min(best.get("dask", 1e9), t)
        assert all(np.array_equal(x, y, equal_nan=True) for x, y in zip(ref, outs)), "maps differ"
    n = len(jobs)
    print(f"{n} tiny pairs (64x48, census, D = 8): one process {best['one'] / n * 1000:.1f} ms/pair, "
          f"Dask 1 worker {best['dask'] / n * 1000:.1f} ms/pair: overhead {(best['dask'] - best['one']) / n * 1000:.1f} "
          "ms per pair (task round trip, image reading on the worker, maps back)")


def huge(args, tmp):
    from distributed import Client

    from mccnn_cl import distributed as dd
    from mccnn_cl.batch import Job
    from mccnn_cl.cli.commands import _gray
    from mccnn_cl.io import read_image, write_image
    from mccnn_cl.pipeline import StereoMatcher
    paths = []
    for side in ("image_2", "image_3"):
        imgs = [read_image(SHARED / side / f"{f}_10.png")[:375, :1242] for f in FRAMES[:4]]
        mosaic = np.vstack([np.hstack(imgs[:2]), np.hstack(imgs[2:])])
        p = os.path.join(tmp, f"huge_{side}.png")
        write_image(p, mosaic)
        paths.append(p)
    job = Job("huge", paths[0], paths[1], os.path.join(tmp, "huge.pfm"))
    D, limit = 128, int(args.huge_limit * 2**20)
    m = StereoMatcher(cost="census", max_disparity=D, memory_limit=limit)
    L, R = _gray(read_image(paths[0])), _gray(read_image(paths[1]))
    plan = m.memory_plan(L.shape)
    print(f"huge image: {L.shape[1]}x{L.shape[0]}, census, D = {D}, --memory-limit {args.huge_limit:g} MiB: "
          f"{plan.describe()}")
    m.compute(L, R)  # warm
    config = dd.matcher_config(cost="census", memory_limit=limit)
    rows = {}
    clusters = {w: (dd.local_cluster(w), None) for w in (1, 2)}
    clients = {w: Client(c) for w, (c, _) in clusters.items()}
    try:
        for w, client in clients.items():  # warm: matchers built, one split run
            list(dd.match_pairs(client, [job], config, D, split_tiles=True))
        for _ in range(args.rounds):
            t = time.perf_counter()
            ref = m.compute(L, R)
            rows.setdefault("one process, tiles in turn", []).append(time.perf_counter() - t)
            for w, client in clients.items():
                t = time.perf_counter()
                [(_, res)] = list(dd.match_pairs(client, [job], config, D, split_tiles=True))
                rows.setdefault(f"Dask, {w} worker(s), tiles split", []).append(time.perf_counter() - t)
                assert np.array_equal(res.disparity, ref, equal_nan=True), "split map differs"
    finally:
        for c in clients.values():
            c.close()
        for c, _ in clusters.values():
            c.close()
    base = min(rows["one process, tiles in turn"])
    for name, ts in rows.items():
        print(f"  {name:34s} {min(ts):7.2f} s  (x{base / min(ts):.2f})   all: "
              + ", ".join(f"{t:.2f}" for t in ts))
    print("  maps equal to the one-process tiled run: yes (bit for bit)")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--cost", choices=("cnn", "census"), default="cnn")
    ap.add_argument("--weights", default="kitti-fst")
    ap.add_argument("--max-disp", type=int, default=228)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--huge-limit", type=float, default=1200, help="MiB: the huge image's memory limit")
    ap.add_argument("--huge-only", action="store_true")
    ap.add_argument("--no-huge", action="store_true")
    ap.add_argument("--overhead-only", action="store_true", help="only the tiny-pair overhead measurement")
    args = ap.parse_args()
    from mccnn_cl.batch import Job
    from mccnn_cl.opencl.context import ClContext
    print(f"machine: {os.cpu_count()} CPU cores ({cpu_name()}), OpenCL {ClContext().describe()}; "
          f"load average at start {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        if args.overhead_only:
            overhead(args, tmp)
            return
        if not args.huge_only:
            jobs = [Job(f, str(SHARED / f"image_2/{f}_10.png"), str(SHARED / f"image_3/{f}_10.png"),
                        os.path.join(tmp, f"{f}.pfm")) for f in FRAMES[:args.pairs]]
            what = f"{args.weights} (cnn)" if args.cost == "cnn" else "census"
            print(f"{len(jobs)} KITTI 2015 pairs (1242x375), {what}, D = {args.max_disp}")
            times, starts, ref = {}, {}, None
            for _ in range(args.rounds):
                t, outs = one_process(jobs, args)
                times.setdefault("one process (mccnn-cl match -l -r)", []).append(t)
                ref = outs
                for w in (1, 2):
                    t, outs, start = on_cluster(jobs, args, w)
                    times.setdefault(f"Dask LocalCluster, {w} worker(s)", []).append(t)
                    starts.setdefault(w, []).append(start)
                    assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(ref, outs)), "maps differ"
            base = min(times["one process (mccnn-cl match -l -r)"])
            for name, ts in times.items():
                print(f"  {name:38s} {min(ts):7.2f} s  {len(jobs) / min(ts):5.2f} pairs/s  (x{base / min(ts):.2f})"
                      "   all: " + ", ".join(f"{t:.2f}" for t in ts))
            one = min(times["Dask LocalCluster, 1 worker(s)"])
            print(f"  Dask overhead per pair (1 worker - one process) / pairs: {(one - base) / len(jobs) * 1000:.0f} ms")
            for w, s in starts.items():
                print(f"  cluster start + warm-up, {w} worker(s): {min(s):.1f} s")
            print("  maps equal to the one-process batch: yes (bit for bit)")
        if not args.no_huge:
            huge(args, tmp)
    print(f"load average at end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
