"""Half-precision volume storage vs float32: accuracy, agreement, time, device memory.

    .venv/bin/python tools/benchmarks/bench_half.py                      # census cost, 4 pairs, ~1 min
    .venv/bin/python tools/benchmarks/bench_half.py --cost cnn --pairs Cones   # the network (slow on a CPU)

For each pair (KITTI: D = 228, 3-px error; Middlebury: its ndisp, bad-2.0),
runs ``StereoMatcher(volume_dtype=...)`` with float32 and float16 storage
(one untimed warm-up each), and prints the error on non-occluded and all
ground-truth pixels, the share of pixels whose disparity is within 0.5 px /
1 px of the float32 map, the wall time and the measured device peak.
Data: ``../shared/data`` or ``$MCCNN_DATA``.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from _paths import data_dir  # noqa: E402

from mccnn_cl.opencl.context import ClContext
from mccnn_cl.evaluation.datasets import discover
from mccnn_cl.pipeline import StereoMatcher

DATA = data_dir()


def error(disp, gt, mask, thr):
    return 100.0 * float(np.mean(np.abs(disp[mask] - gt[mask]) > thr))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cost", choices=("census", "cnn"), default="census")
    ap.add_argument("--pairs", default="kitti2012/000000,kitti2015/000000,Cones,Motorcycle")
    ap.add_argument("--device", default=None)
    args = ap.parse_args(argv)
    ctx = ClContext(args.device)
    print(f"device: {ctx.describe()}; cost {args.cost}; load average {os.getloadavg()[0]:.1f}")
    wanted = [n for n in args.pairs.split(",") if n]
    refs = [r for r in discover(DATA) if any(n in r.key for n in wanted)]
    if not refs:
        raise SystemExit(f"no pair among {wanted} under {DATA}")
    print("| pair, D | error float32 -> float16 (noc / all) | within 0.5 px / 1 px of float32 "
          "| time float32 -> float16 | device peak float32 -> float16 |")
    print("|---|---|---|---|---|")
    for ref in refs:
        p = ref.load()
        kitti = ref.kind.startswith("kitti")
        D, thr = (228, 3.0) if kitti else (int(p.ndisp or 128), 2.0)
        runs = {}
        for dt in ("float32", "float16"):
            m = StereoMatcher(cost=args.cost, max_disparity=D, device=ctx, volume_dtype=dt)
            m.compute(p.left, p.right)  # warm-up: program builds
            t0 = time.perf_counter()
            res = m.compute(p.left, p.right, timings=True)
            runs[dt] = (res, time.perf_counter() - t0)
        valid = np.isfinite(p.disp)
        noc = p.valid_noc if p.valid_noc is not None else valid
        errs = {dt: (error(r.disparity, p.disp, noc, thr), error(r.disparity, p.disp, valid, thr))
                for dt, (r, _) in runs.items()}
        diff = np.abs(runs["float32"][0].disparity - runs["float16"][0].disparity)
        (a, ta), (b, tb) = runs["float32"], runs["float16"]
        print(f"| {ref.key}, {D} | {errs['float32'][0]:.2f} / {errs['float32'][1]:.2f} -> "
              f"{errs['float16'][0]:.2f} / {errs['float16'][1]:.2f} % | {100 * np.mean(diff <= 0.5):.2f} / "
              f"{100 * np.mean(diff <= 1):.2f} % | {ta:.2f} -> {tb:.2f} s | "
              f"{a.peak_device_bytes / 2**20:.0f} -> {b.peak_device_bytes / 2**20:.0f} MiB |", flush=True)


if __name__ == "__main__":
    main()
