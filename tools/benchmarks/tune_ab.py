"""Tuning on / off, A/B in one process, on a KITTI 2015 pair; the stages'
ratios to their floors measured in the same run; a never-seen size and D
after a warm-up; fresh ``mccnn-cl match`` processes (``--one-off N``, each against
the steady call just before it).

    .venv/bin/python tools/benchmarks/tune_ab.py [--data ../shared/data] [--repeat 3] [--costs cnn,cnn:kitti-fst,census] [--one-off 3]

Tuning "on" applies the device's stored choices (run ``mccnn-cl tune``
first); "off" the rules table.  Each configuration gets its own matcher;
the runs alternate (on, off, on, off ...) and the best time per stage is kept.
Prints markdown tables (BENCHMARKS.md, "Tuning, builds and first calls").
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

import mccnn_cl
from mccnn_cl import StereoMatcher
from mccnn_cl.opencl import tune
from mccnn_cl.benchmark import (copy_bandwidth, floors as bench_floors, group_timings, host_gemm_applies,
                                numpy_gemm_rate, volume_bytes)
from mccnn_cl.opencl.context import ClContext

from _paths import data_dir  # noqa: E402


def floors(m, shape, vol, copy_bw, gemm):
    """Per group: the floor in seconds (mccnn_cl.benchmark.floors, bench's definitions: the network's
    FLOP at the host CPU's numpy GEMM rate, only where the device is that CPU; the volume traffic,
    reads + writes, at the copy rate)."""
    return bench_floors(m, shape, vol, copy_bw, gemm if host_gemm_applies(m.ctx) else None)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(data_dir()), help="shared data (default: $MCCNN_DATA, else ../shared/data)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--one-off", type=int, default=3, metavar="N",
                    help="fresh `mccnn-cl match` processes to time, each against the steady call just before it")
    ap.add_argument("--costs", default="cnn,cnn:kitti-fst,census",
                    help="comma-separated: cnn (the default network), cnn:WEIGHTS (e.g. cnn:kitti-fst, the "
                         "speed issue's own benchmark), census")
    args = ap.parse_args()
    k = Path(args.data) / "kitti2015" / "training"
    lp, rp = k / "image_2" / "000000_10.png", k / "image_3" / "000000_10.png"
    L, R = cv2.imread(str(lp), 0), cv2.imread(str(rp), 0)
    D = 228
    ctx = ClContext()
    stored = tune.load(ctx.device)
    print(f"device: {ctx.describe()}")
    print(f"stored choices: {stored or 'none (run mccnn-cl tune)'}")
    copy_bw, gemm = copy_bandwidth(ctx), numpy_gemm_rate()
    print(f"in-run baselines (each best of 3): device copy {copy_bw / 1e9:.1f} GB/s (read + write counted), "
          f"host CPU numpy GEMM {gemm / 1e9:.0f} GFLOP/s; load average (1 min) {os.getloadavg()[0]:.2f}, "
          f"{os.cpu_count()} cores")
    for entry in args.costs.split(","):
        cost, _, weights = entry.partition(":")  # "cnn" (the default network), "cnn:kitti-fst", "census"
        extra = {"weights": weights} if weights else {}
        matchers = {}
        for mode in ("on", "off"):
            ctx.profile.tuned.clear()
            if mode == "on":
                ctx.profile.tuned.update(stored)
            m = StereoMatcher(cost=cost, max_disparity=D, device=ctx, **extra)
            m.compute(L, R)  # warm-up: builds, first touch
            matchers[mode] = m
        best = {"on": {}, "off": {}}
        for _ in range(args.repeat):
            for mode, m in matchers.items():
                ctx.profile.tuned.clear()
                if mode == "on":
                    ctx.profile.tuned.update(stored)
                t = time.perf_counter()
                res = m.compute(L, R, timings=True)
                total = time.perf_counter() - t
                g = group_timings(res.timings)
                g["total"] = total
                for name, sec in g.items():
                    best[mode][name] = min(best[mode].get(name, 9e9), sec)
            # volumes of one matcher are freed before the other runs (memory)
        m = matchers["on"]
        vol = volume_bytes(m, L.shape, D)
        fl = floors(m, L.shape, vol, copy_bw, gemm)
        fl["total"] = sum(fl.values())
        print(f"\n{entry}: best of {args.repeat}, KITTI 2015 000000 (1242x375), D {D}")
        print("| stage | floor | tuning on | ratio | tuning off | ratio |")
        print("|---|---|---|---|---|---|")
        for name in ("cost", "CBCA", "SGM", "rest", "total"):
            if name not in fl or fl[name] == 0:
                if best["on"].get(name, 0) > 0.001:
                    print(f"| {name} | - | {best['on'][name]:.3f} s | - | {best['off'][name]:.3f} s | - |")
                continue
            on, off = best["on"][name], best["off"][name]
            print(f"| {name} | {fl[name]:.3f} s | {on:.3f} s | {on / fl[name]:.2f}x | {off:.3f} s | "
                  f"{off / fl[name]:.2f}x |")
        for mm in matchers.values():
            mm.release_buffers()
        matchers.clear()

    # a size and D never seen, after the warm-up above (tuning as stored)
    ctx.profile.tuned.clear()
    ctx.profile.tuned.update(stored)
    m = StereoMatcher(max_disparity=D, device=ctx)
    m.compute(L, R)
    b0 = ctx.builds + ctx.binary_loads
    m.max_disparity = 201
    Ln, Rn = L[10:351, 30:1131], R[10:351, 30:1131]
    t = time.perf_counter()
    m.compute(Ln, Rn)
    first = time.perf_counter() - t
    reps = []
    for _ in range(2):
        t = time.perf_counter()
        m.compute(Ln, Rn)
        reps.append(time.perf_counter() - t)
    print(f"\nnew size 1101x341, D 201 after a KITTI warm-up (fst): first call {first:.2f} s, repeated "
          f"{min(reps):.2f} s, ratio {first / min(reps):.2f} (target <= 1.2 + 0.3 s / repeated: "
          f"{first <= 1.2 * min(reps) + 0.3}); programs made for it: {ctx.builds + ctx.binary_loads - b0}")
    m.max_disparity = D
    # the package's bytecode, as a Python that writes it keeps it after a first run (where
    # PYTHONDONTWRITEBYTECODE is set, as on these VMs, each process would compile ~45 modules: ~0.07 s)
    subprocess.run([sys.executable, "-m", "compileall", "-q", *mccnn_cl.__path__], check=True, capture_output=True)
    # fresh `mccnn-cl match` processes on the KITTI pair, each against the steady call of this process just
    # before it (the VM's speed drifts between minutes: a ratio per round, not one number); this process's
    # buffers are freed while the fresh one runs
    ratios = []
    for r in range(args.one_off):
        m.compute(L, R)
        t = time.perf_counter()
        m.compute(L, R)
        steady = time.perf_counter() - t
        m.release_buffers()
        with tempfile.TemporaryDirectory() as tmp:
            out = os.path.join(tmp, "d.pfm")
            cmd = [sys.executable, "-m", "mccnn_cl", "match", str(lp), str(rp), "-o", out, "--max-disp", str(D)]
            t = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True)
            wall = time.perf_counter() - t
        ratios.append(wall / steady)
        print(f"mccnn-cl match, one KITTI pair, fresh process {r + 1}/{args.one_off}: {wall:.2f} s wall; steady "
              f"compute here just before {steady:.2f} s; ratio {wall / steady:.2f} (target <= 1.3)")
    if len(ratios) > 1:
        print(f"one-off ratios: {', '.join(f'{x:.2f}' for x in sorted(ratios))} (target <= 1.3)")

if __name__ == "__main__":
    main()
