"""Benchmark of the JMLR networks' costs (fst, acrt) and of the fst stereo method.

    python tools/benchmarks/bench_fst.py [--arch fst|acrt] [--disp 228] [--device SPEC] [--weights FILE]

On the KITTI 2015 pair 000000 (1242 x 375, gray) of the shared data, after
a warm-up, best of ``--reps`` runs, each timed after ``ctx.finish()``:

* features: the conv stack of both images (fst: and the L2 normalisation;
  acrt: and the L4 split), against numpy's float32 GEMM (OpenBLAS, on the
  host CPU) on the same arithmetic: per layer the im2col product (pixels x
  k*k*cin) @ (k*k*cin x maps), both images, the shapes printed (the im2col
  copies and the products' outputs are made beforehand and not timed, so
  numpy gets the bare BLAS rate);
* fst volume: the cosine-volume kernel alone on features already on the
  device.  It writes the volume and reads only the features, so its floor
  is a write-only pass over a buffer of the volume's size: a fill
  (clEnqueueFillBuffer), printed as the floor.  A copy (clEnqueueCopyBuffer,
  read + write) is printed beside it in bench's one convention: GB/s count
  the bytes read + written (a copy moves 2 x its size), and the volume's
  write at that rate (its V bytes over the copy's rate) is the copy-rate
  floor.  Copy and fill are timed by OpenCL profiling events
  (mccnn_cl.benchmark.device_seconds), not through the polling wait;
* acrt head: its FLOP rate against numpy GEMM on one hidden layer's shape
  (named in the output);
* the whole stereo method (``StereoMatcher(weights=...)`` with the
  network's own settings, default the authors' KITTI ones), steady state
  (volumes kept between calls), with the per-stage split of one timed call;
* fst, unless ``--no-gpu-shaped``: the GPU-shaped kernels (the gpu column's
  default: the conv stack as a local-memory tiled GEMM, network_conv_wg.cl;
  the work-group volume, fst_wg.cl) forced on this device, timed in turn
  with the features and the volume kernel of this device's default, with
  which their outputs are checked bit for bit.  On a CPU they are expected
  to be slower (PoCL runs a group's work-items as loops between barriers):
  the line is there to be read on a GPU.

Weights are random of the authors' KITTI sizes unless ``--weights`` names a
file (run time does not depend on the values).  The figures in
BENCHMARKS.md come from this script.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bench_network import cpu_name
from mccnn_cl.benchmark import device_seconds


def best(fn, reps):
    t = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return min(t)


def interleaved(fns, reps):
    """Best time of each function, the functions run in turn in every round
    (so that drifts of this shared machine's speed hit them alike).  A
    function that returns a number has timed itself (seconds: e.g. by
    OpenCL profiling events); that number is taken instead of the wall time."""
    times = {name: [] for name in fns}
    for _ in range(reps):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            got = fn()
            wall = time.perf_counter() - t0
            times[name].append(float(got) if isinstance(got, (int, float)) else wall)
    return {name: min(t) for name, t in times.items()}


def gemm_shapes(w, H, W, extra=None):
    """(rows, k, n) of numpy's GEMMs with the conv stack's im2col shapes (one
    image), plus ``extra`` products."""
    shapes = []
    h, wd = H, W
    for Wc, _ in w.conv:
        cout, cin, k, _ = Wc.shape
        h, wd = h - k + 1, wd - k + 1
        shapes.append((h * wd, k * k * cin, cout))
    return shapes + list(extra or [])


def shapes_text(shapes) -> str:
    """'(m x k) @ (k x n)' per distinct shape, with its count."""
    out, seen = [], {}
    for s in shapes:
        seen[s] = seen.get(s, 0) + 1
    for (m, k, n), c in seen.items():
        out.append(f"({m} x {k}) @ ({k} x {n})" + (f" x{c}" if c > 1 else ""))
    return ", ".join(out)


def gemm_job(w, H, W, reps, extra=None):
    """numpy's GEMMs with the conv stack's shapes (both images), plus
    ``extra`` (rows, k, n) products, each into an output kept between runs;
    returns (a function running them, FLOP, the shapes of one image)."""
    rng = np.random.default_rng(0)
    shapes = gemm_shapes(w, H, W, extra)
    mats = [(rng.random((m, k), np.float32), rng.random((k, n), np.float32), np.empty((m, n), np.float32))
            for m, k, n in shapes]
    flop = 2 * sum(2 * m * k * n for m, k, n in shapes)

    def run():
        for _ in range(2):  # both images
            for a, b, c in mats:
                np.matmul(a, b, out=c)
    run()
    return run, flop, shapes


def volume_vs_floors(nbytes, t_vol, t_copy, t_fill) -> dict:
    """The volume kernel against its floors, in bench's one convention (GB/s
    count bytes read + written): it writes ``nbytes`` (the features it reads
    are small), so its floor is a write-only pass, the fill's time; the copy
    moves 2 x nbytes, and the volume's write at the copy's rate takes
    nbytes / that rate (half the copy's time)."""
    copy_rate = 2.0 * nbytes / t_copy
    return {"vol_rate": nbytes / t_vol, "copy_rate": copy_rate, "fill_rate": nbytes / t_fill,
            "floor_fill": t_fill, "floor_copy": nbytes / copy_rate,
            "ratio_fill": t_vol / t_fill, "ratio_copy": t_vol / (nbytes / copy_rate)}


def gpu_shaped(ctx, cost, w, Ln, Rn, h, wd, D, reps):
    """fst's GPU-shaped kernels forced (``FstCost(local_tiles=True,
    workgroup=True)``) against ``cost`` (this device's default): features
    and volume, each pair timed in turn; outputs compared bit for bit."""
    from mccnn_cl.costs.fst import FstCost

    gpu = FstCost(ctx, w, local_tiles=True, workgroup=True)
    if gpu.volume_path == cost.volume_path and gpu.stack.path == cost.stack.path:
        print("GPU-shaped kernels: this device's default already (timed above)")
        return
    nbytes = D * h * wd * 4
    vols = [ctx.empty(nbytes, "bench volume") for _ in range(2)]
    feats = {}

    def features(c):
        def run():
            for b in feats.pop(c, ()):
                b.release()
            feats[c] = (c._features(Ln, h, wd), c._features(Rn, h, wd))
            ctx.finish()
        return run

    def volume(c, d_vol):
        def run():
            c.launch_volume(*feats[c], d_vol, h, wd, 0, D, h)
            ctx.finish()
        return run

    for c in (cost, gpu):
        features(c)()
    t = interleaved({"default": features(cost), "gpu": features(gpu)}, reps)
    tiles = sorted({str(l[0].tile) for l in gpu.stack.layers})
    print(f"features, GPU-shaped (network_conv_wg, tiles {', '.join(tiles)}): {t['gpu'] * 1e3:.0f} ms against "
          f"{t['default'] * 1e3:.0f} ms ({cost.stack.path} conv): {t['gpu'] / t['default']:.2f}x")
    t = interleaved({"default": volume(cost, vols[0]), "gpu": volume(gpu, vols[1])}, reps)

    def host(buf):
        return ctx.from_device(buf, (buf.size // 4,), np.uint32)

    same = np.array_equal(host(vols[0]), host(vols[1])) and all(
        np.array_equal(host(a), host(b)) for a, b in zip(feats[cost], feats[gpu]))
    print(f"cosine volume, GPU-shaped (fst_volume_wg, tile {gpu.volume_tile}): {t['gpu'] * 1e3:.0f} ms against "
          f"{t['default'] * 1e3:.0f} ms (fst_volume_{cost.volume_path}): {t['gpu'] / t['default']:.2f}x; "
          f"features and volume bit-identical: {same}")
    for b in vols + [b for pair in feats.values() for b in pair]:
        b.release()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", choices=("fst", "acrt"), default="fst")
    ap.add_argument("--disp", type=int, default=228)
    ap.add_argument("--device", default=None)
    ap.add_argument("--weights", default=None, help="a weights file (default: random, authors' sizes)")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--no-pipeline", action="store_true")
    ap.add_argument("--no-gpu-shaped", action="store_true",
                    help="fst: skip timing the GPU-shaped kernels forced beside this device's default")
    args = ap.parse_args(argv)

    from mccnn_cl.evaluation import datasets
    from mccnn_cl.opencl.context import ClContext
    from mccnn_cl.pipeline import StereoMatcher, to_gray
    from mccnn_cl.settings import authors_settings
    from mccnn_cl.costs.registry import make_cost
    from mccnn_cl.costs.features import normalise
    from mccnn_cl.models import resolve
    from mccnn_cl.weights import Weights

    from _paths import data_dir

    data = str(data_dir())
    pair = datasets.load_kitti2015(os.path.join(data, "kitti2015", "training"), "000000")
    left, right = to_gray(pair.left, "left"), to_gray(pair.right, "right")
    H, W = left.shape
    D = args.disp
    arch = "mccnn-" + args.arch
    if args.weights:
        w = resolve(args.weights)
    else:
        w = Weights.random(architecture=arch, seed=1)
        w.meta["stereo"] = authors_settings(arch, "kitti")
    ctx = ClContext(args.device)
    print(f"machine: {cpu_name()}, {os.cpu_count()} CPUs; load average {os.getloadavg()}")
    print(f"OpenCL: {ctx.describe()}")
    cost = make_cost(ctx, w)
    m = cost.margin
    h, wd = H - 2 * m, W - 2 * m
    print(f"{arch} {w.conv_layers()} {w.fc_layers()}; KITTI 2015 000000 {W}x{H}, D = {D}; volume "
          f"{D}x{h}x{wd} = {D * h * wd * 4 / 1e6:.0f} MB")
    cost(left[:40, :80], right[:40, :80], 8).release()  # warm-up: programs built
    fl = cost.flops(H, W, D)

    Ln, Rn = normalise(left)[:, :, None], normalise(right)[:, :, None]
    if args.arch == "fst":
        def feats():
            a, b = cost._features(Ln, h, wd), cost._features(Rn, h, wd)
            ctx.finish()
            return a, b
        extra = []
    else:
        def feats():
            a, b = cost._half(Ln, True), cost._half(Rn, False)
            ctx.finish()
            return a, b
        extra = [(h * wd, w.feature_maps, w.fc[0][0].shape[0])]
    for buf in feats():
        buf.release()
    np_run, np_flop, np_shapes = gemm_job(w, H, W, args.reps, extra)
    t = interleaved({"features": lambda: [b.release() for b in feats()], "numpy": np_run}, args.reps)
    t_feat, t_np = t["features"], t["numpy"]
    print(f"features: {t_feat * 1e3:.0f} ms ({fl['features'] / t_feat / 1e9:.1f} GFLOP/s); host CPU numpy "
          f"float32 GEMM on the same im2col shapes, both images [{shapes_text(np_shapes)}], outputs kept: "
          f"{t_np * 1e3:.0f} ms ({np_flop / t_np / 1e9:.1f} GFLOP/s): ratio {t_feat / t_np:.2f}x "
          f"(best of {args.reps}, interleaved)")

    if args.arch == "fst":
        nbytes = D * h * wd * 4
        d_vol = ctx.empty(nbytes, "bench volume")
        d_src = ctx.empty(nbytes, "bench copy source")
        ctx.fill(d_src, 0.0, nbytes)
        ctx.fill(d_vol, 0.0, nbytes)
        d_l, d_r = feats()

        def vol():
            cost.launch_volume(d_l, d_r, d_vol, h, wd, 0, D, h)
            ctx.finish()

        # copy and fill: short device operations, timed by profiling events (no polling wait in them)
        timers = set()

        def copy():
            sec, how = device_seconds(ctx, lambda q: ctx.cl.enqueue_copy(q, d_vol, d_src, byte_count=nbytes),
                                      repeat=1, warmup=False)
            timers.add(how)
            return sec

        def fill():
            pattern = np.array([1.0], np.float32)
            sec, how = device_seconds(ctx, lambda q: ctx.cl.enqueue_fill_buffer(q, d_vol, pattern, 0, nbytes),
                                      repeat=1, warmup=False)
            timers.add(how)
            return sec
        vol()
        copy()
        fill()
        t = interleaved({"vol": vol, "copy": copy, "fill": fill}, args.reps)
        r = volume_vs_floors(nbytes, t["vol"], t["copy"], t["fill"])
        print(f"cosine volume: {t['vol'] * 1e3:.0f} ms ({r['vol_rate'] / 1e9:.2f} GB/s written, "
              f"{fl['volume'] / t['vol'] / 1e9:.1f} GFLOP/s), best of {args.reps}; its floor, write-only: a fill "
              f"of the {nbytes / 1e6:.0f} MB volume {r['floor_fill'] * 1e3:.1f} ms ({r['fill_rate'] / 1e9:.2f} GB/s "
              f"written): volume / fill {r['ratio_fill']:.2f}x")
        print(f"  beside it, bench's convention (GB/s count bytes read + written): copy of {nbytes / 1e6:.0f} MB "
              f"{t['copy'] * 1e3:.1f} ms ({r['copy_rate'] / 1e9:.2f} GB/s read + write); the volume's write at "
              f"that rate {r['floor_copy'] * 1e3:.1f} ms: volume / that {r['ratio_copy']:.2f}x (copy and fill "
              f"timed by {', '.join(sorted(timers))})")
        print(f"  its arithmetic at the host CPU numpy GEMM rate above (the conv stack's im2col shapes): "
              f"{fl['volume'] / (np_flop / t_np) * 1e3:.0f} ms")
        for b in (d_vol, d_src, d_l, d_r):
            b.release()
        t_cost = best(lambda: (cost(left, right, D).release(), ctx.finish()), args.reps)
        print(f"whole cost (features + volume, fresh volume buffer): {t_cost * 1e3:.0f} ms")
        if not args.no_gpu_shaped:
            gpu_shaped(ctx, cost, w, Ln, Rn, h, wd, D, args.reps)
    else:
        t_cost = best(lambda: (cost(left, right, D).release(), ctx.finish()), 1)
        head = t_cost - t_feat
        hrows = h * wd
        hk = w.fc[1][0].shape[1] if len(w.fc) > 2 else w.fc[0][0].shape[0]
        a = np.random.default_rng(0).random((hrows, hk), np.float32)
        b = np.random.default_rng(1).random((hk, hk), np.float32)
        c = np.empty((hrows, hk), np.float32)
        np.matmul(a, b, out=c)  # warm-up; the output kept
        t_g = best(lambda: np.matmul(a, b, out=c), args.reps)
        g_rate = 2 * hrows * hk * hk / t_g / 1e9
        print(f"acrt cost {t_cost:.2f} s: head ~{head:.2f} s ({fl['head'] / head / 1e9:.1f} GFLOP/s; host CPU numpy "
              f"float32 GEMM ({hrows} x {hk}) @ ({hk} x {hk}), best of {args.reps}: {g_rate:.1f} GFLOP/s, "
              f"head/GEMM rate {fl['head'] / head / 1e9 / g_rate:.2f}x)")

    if args.no_pipeline:
        return
    sm = StereoMatcher(weights=w, max_disparity=D, device=ctx)
    sm.compute(pair.left, pair.right)  # warm-up: builds, volumes allocated
    t_pipe = best(lambda: sm.compute(pair.left, pair.right), args.reps)
    res = sm.compute(pair.left, pair.right, timings=True)
    stages = ", ".join(f"{k} {v * 1e3:.0f}" for k, v in res.timings.items())
    print(f"stereo method ({args.arch}, its settings) steady state: {t_pipe:.3f} s; one timed call "
          f"{sum(res.timings.values()):.3f} s: {stages} (ms)")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
