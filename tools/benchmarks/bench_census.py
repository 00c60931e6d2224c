"""Timing of the census matching cost on a KITTI-sized pair: the whole stage
(both census transforms, the cost volume, uploads) and one transform alone,
best of ``--repeat`` after a warm-up, beside the buffer-copy bandwidth
measured in the same run (the volume's write at that rate is the floor).

    .venv/bin/python tools/benchmarks/bench_census.py [--repeat 5] [--size 1242x375] [--D 228]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from mccnn_cl.benchmark import copy_bandwidth, synthetic_pair
from mccnn_cl.costs.census import MARGIN, CensusCost
from mccnn_cl.opencl.context import ClContext, launch


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="1242x375")
    ap.add_argument("--D", type=int, default=228)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    Wi, Hi = (int(v) for v in args.size.lower().split("x"))
    D = args.D
    ctx = ClContext()
    left, right = (a.astype(np.float32) for a in synthetic_pair(Wi, Hi, D))
    H, W = Hi - 2 * MARGIN, Wi - 2 * MARGIN
    cost = CensusCost(ctx)
    out = ctx.empty(4 * D * H * W, "census volume")
    d_img, d_bits = ctx.to_device(left), ctx.empty(3 * H * W * 4, "census bits")

    def stage():
        cost(left, right, D, out=out)

    def transform():
        launch(ctx, "census transform", cost.k_transform, (W, H), d_img, d_bits, np.int32(H), np.int32(W))

    best = {}
    for name, fn in (("stage", stage), ("transform", transform)):
        fn()
        ctx.finish()
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            fn()
            ctx.finish()
            best[name] = min(best.get(name, float("inf")), time.perf_counter() - t0)
    bw = copy_bandwidth(ctx)
    vol = 4 * D * H * W
    print(f"device: {ctx.describe()}; load average {os.getloadavg()[0]:.1f}")
    print(f"census stage ({Wi}x{Hi}, D {D}, {vol / 2**20:.0f} MiB volume): {best['stage'] * 1e3:.1f} ms; "
          f"one transform {best['transform'] * 1e3:.1f} ms; volume write at the copy rate "
          f"({bw / 1e9:.2f} GB/s) {vol / bw * 1e3:.1f} ms: {best['stage'] / (vol / bw):.2f}x")


if __name__ == "__main__":
    main()
