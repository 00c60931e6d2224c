"""Benchmark of the network stage (C_CNN) against torch and numpy on the CPU.

    python tools/benchmarks/bench_network.py [--height 376 --width 1240 --disp 64]

Times, after a warm-up (programs built, buffers touched):

* OpenCL: ``NetworkCost(ctx, w)(left, right, D)`` end to end (normalise,
  upload, L1-L3 + L4 split for both images, the fused per-disparity head),
  with the feature part timed separately;
* torch (CPU, its default thread count): the same computation, features
  fully convolutionally then the head batched per disparity
  (:func:`mccnn_cl.reference.network.cost_volume_torch`);
* numpy's float32 GEMM (OpenBLAS) on the head's shapes: (pixels x 300) @
  (300 x 300), the rate an ideal BLAS-bound implementation would get.

FLOP counts are exact for the work done (valid cells only, x >= d): 2 per
multiply-add plus the L4 addition.  Weights are random of the paper's size;
run time does not depend on their values.  Prints figures and ratios; the
numbers in BENCHMARKS.md come from this script.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np


def flop_counts(w, H, W, D):
    """(features FLOP for both images, head FLOP, valid cells) for an H x W pair and D disparities."""
    feat = 0
    h, wd = H, W
    for Wc, _ in w.conv:
        cout, cin, k, _ = Wc.shape
        h, wd = h - k + 1, wd - k + 1
        feat += 2 * h * wd * cout * cin * k * k
    maps, n4 = w.feature_maps, w.fc[0][0].shape[0]
    feat += 2 * h * wd * maps * n4          # A or B: half of L4, once per pixel
    feat *= 2                               # left and right
    cells = sum(h * max(wd - d, 0) for d in range(D))
    per_cell = n4 + sum(2 * Wf.shape[0] * Wf.shape[1] for Wf, _ in w.fc[1:])
    return feat, cells * per_cell, cells


class Timer:
    """Wall-clock and process CPU time (all threads of this process) of a block."""

    def __enter__(self):
        self.w0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self.w0
        self.cpu = time.process_time() - self.c0


def rates(flop, t):
    """'X GFLOP/s wall, Y GFLOP/s per CPU-second' for a Timer."""
    return (f"{flop / t.wall / 1e9:.1f} GFLOP/s wall, "
            f"{flop / max(t.cpu, 1e-9) / 1e9:.1f} GFLOP/s per CPU-second")


def cpu_name():
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--height", type=int, default=376)
    ap.add_argument("--width", type=int, default=1240)
    ap.add_argument("--disp", type=int, default=64, help="disparity levels D")
    ap.add_argument("--device", default=None, help="OpenCL device spec (see mccnn_cl.opencl.context.select_device)")
    ap.add_argument("--no-torch", action="store_true", help="skip the torch timing")
    ap.add_argument("--torch-disp", type=int, default=0,
                    help="time torch on the first N disparities only (default: all D); rates and "
                         "ratios are per FLOP, so they stay comparable")
    ap.add_argument("--gemm-rows", type=int, default=0,
                    help="rows of the numpy GEMM (default: the valid cells of one disparity)")
    args = ap.parse_args(argv)

    from mccnn_cl.opencl.context import ClContext
    from mccnn_cl.costs.network import NetworkCost
    from mccnn_cl.weights import Weights

    H, W, D = args.height, args.width, args.disp
    rng = np.random.default_rng(0)
    left = (rng.random((H, W)) * 255).astype(np.float32)
    right = np.roll(left, -5, axis=1)
    w = Weights.random(seed=1)
    feat_flop, head_flop, cells = flop_counts(w, H, W, D)
    total_flop = feat_flop + head_flop

    ctx = ClContext(args.device)
    print(f"machine: {cpu_name()}, {os.cpu_count()} CPUs; load average {os.getloadavg()}")
    print(f"OpenCL: {ctx.describe()}")
    print(f"input {H}x{W}, D = {D}, paper-size random net; cost volume {D}x{H - 8}x{W - 8}, "
          f"{cells:,} valid cells")
    print(f"FLOP: features {feat_flop:.3e} + head {head_flop:.3e} = {total_flop:.3e}")

    net = NetworkCost(ctx, w)
    tiles = (f"tiles TM={net.tm} RM={net.rm} RN={net.rn} HP={net.hp}, {net.nwi} work-items/group"
             if net.head_path == "fused" else f"layer by layer, RN={net.rn} HP={net.hp}")
    print(f"head: {net.head_path} ({tiles}); conv: {net.stack.path}")
    t0 = time.perf_counter()
    net(left[:64, :128], right[:64, :128], 4).release()  # warm-up: builds, first launches
    print(f"warm-up {time.perf_counter() - t0:.2f} s")

    # features alone (both images), then the full call
    from mccnn_cl.costs.network import normalise
    P = w.patch_size
    rows = net.band_rows(H - P + 1, W - P + 1)
    print(f"bands of {rows} volume rows")
    with Timer() as tf:
        for img, is_left in ((left, True), (right, False)):
            n = normalise(img)[:, :, None]
            for y0 in range(0, H - P + 1, rows):
                net._half(n[y0:y0 + rows + P - 1], is_left).release()
        ctx.finish()
    with Timer() as tc:
        d_cost = net(left, right, D)
        ctx.finish()
    head_wall, head_cpu = max(tc.wall - tf.wall, 1e-9), max(tc.cpu - tf.cpu, 1e-9)
    print(f"OpenCL: total {tc.wall:.2f} s wall ({tc.cpu:.2f} s CPU): {rates(total_flop, tc)}")
    print(f"  features {tf.wall:.2f} s: {rates(feat_flop, tf)}")
    print(f"  head ~{head_wall:.2f} s: {head_flop / head_wall / 1e9:.1f} GFLOP/s wall, "
          f"{head_flop / head_cpu / 1e9:.1f} GFLOP/s per CPU-second")
    cl_rate = total_flop / tc.wall / 1e9
    cl_rate_cpu = total_flop / tc.cpu / 1e9

    # numpy GEMM on the head's shapes
    rows = args.gemm_rows or (H - 8) * (W - 8)
    a = rng.random((rows, w.fc[1][0].shape[1])).astype(np.float32)
    b = rng.random((w.fc[1][0].shape[1], w.fc[1][0].shape[0])).astype(np.float32)
    c = np.empty((rows, b.shape[1]), np.float32)  # one output kept: no fresh allocation timed
    np.matmul(a, b, out=c)
    reps = 3
    gemm_flop = reps * 2 * rows * b.shape[0] * b.shape[1]
    with Timer() as tn:
        for _ in range(reps):
            np.matmul(a, b, out=c)
    print(f"host CPU numpy GEMM ({rows}x{b.shape[0]}) @ ({b.shape[0]}x{b.shape[1]}) float32, output kept: "
          f"{rates(gemm_flop, tn)}")
    np_rate, np_rate_cpu = gemm_flop / tn.wall / 1e9, gemm_flop / tn.cpu / 1e9
    del a, b, c

    if not args.no_torch:
        import torch

        from mccnn_cl.reference.network import cost_volume_torch
        from mccnn_cl.train.model import MCCNN
        model = MCCNN.from_weights(w).eval()
        Dt = min(args.torch_disp or D, D)
        ft, ht, _ = flop_counts(w, H, W, Dt)
        cost_volume_torch(w, left[:64, :128], right[:64, :128], 4, model=model)  # warm-up
        with Timer() as tt:
            vol_t = cost_volume_torch(w, left, right, Dt, model=model)
        vol_cl = ctx.from_device(d_cost, (D, H - 8, W - 8))[:Dt]
        err = np.nanmax(np.abs(vol_cl - vol_t))
        same_nan = np.array_equal(np.isnan(vol_cl), np.isnan(vol_t))
        print(f"torch {torch.__version__} ({torch.get_num_threads()} threads), D = {Dt}: "
              f"{tt.wall:.2f} s wall ({tt.cpu:.2f} s CPU): {rates(ft + ht, tt)}; "
              f"max |OpenCL - torch| = {err:.2e}, NaN positions {'equal' if same_nan else 'DIFFER'}")
        t_rate, t_rate_cpu = (ft + ht) / tt.wall / 1e9, (ft + ht) / tt.cpu / 1e9
        print(f"ratio OpenCL/torch (FLOP rate): {cl_rate / t_rate:.2f}x wall, "
              f"{cl_rate_cpu / t_rate_cpu:.2f}x per CPU-second")
    print(f"ratio OpenCL/numpy GEMM (FLOP rate): {cl_rate / np_rate:.2f}x wall, "
          f"{cl_rate_cpu / np_rate_cpu:.2f}x per CPU-second "
          f"(head alone {head_flop / head_wall / 1e9 / np_rate:.2f}x wall)")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
