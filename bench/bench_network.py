"""Benchmark of the network stage (C_CNN) against torch and numpy on the CPU.

    python bench/bench_network.py [--height 376 --width 1240 --disp 64]

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
    ap.add_argument("--device", default=None, help="OpenCL device spec (see mccnn_cl.cl.select_device)")
    ap.add_argument("--no-torch", action="store_true", help="skip the torch timing")
    ap.add_argument("--gemm-rows", type=int, default=0,
                    help="rows of the numpy GEMM (default: the valid cells of one disparity)")
    args = ap.parse_args(argv)

    from mccnn_cl.cl import ClContext
    from mccnn_cl.stages.network import NetworkCost
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
    print(f"tiles: TM={net.tm} RM={net.rm} RN={net.rn} HP={net.hp}, {net.nwi} work-items/group")
    t0 = time.perf_counter()
    net(left[:64, :128], right[:64, :128], 4).release()  # warm-up: builds, first launches
    print(f"warm-up {time.perf_counter() - t0:.2f} s")

    # features alone (both images), then the full call
    Lf = left.astype(np.float64)[:, :, None]
    t0 = time.perf_counter()
    for side in ("left", "right"):
        net._side(Lf, side).release()
    ctx.finish()
    t_feat = time.perf_counter() - t0
    t0 = time.perf_counter()
    d_cost = net(left, right, D)
    ctx.finish()
    t_cl = time.perf_counter() - t0
    t_head = max(t_cl - t_feat, 1e-9)
    print(f"OpenCL: total {t_cl:.2f} s = {total_flop / t_cl / 1e9:.1f} GFLOP/s; "
          f"features {t_feat:.2f} s ({feat_flop / t_feat / 1e9:.1f} GFLOP/s), "
          f"head ~{t_head:.2f} s ({head_flop / t_head / 1e9:.1f} GFLOP/s)")

    # numpy GEMM on the head's shapes
    rows = args.gemm_rows or (H - 8) * (W - 8)
    a = rng.random((rows, w.fc[1][0].shape[1])).astype(np.float32)
    b = rng.random((w.fc[1][0].shape[1], w.fc[1][0].shape[0])).astype(np.float32)
    a @ b
    reps = 3
    t0 = time.perf_counter()
    for _ in range(reps):
        a @ b
    t_np = (time.perf_counter() - t0) / reps
    np_rate = 2 * rows * b.shape[0] * b.shape[1] / t_np / 1e9
    print(f"numpy GEMM ({rows}x{b.shape[0]}) @ ({b.shape[0]}x{b.shape[1]}) float32: {np_rate:.1f} GFLOP/s")
    del a, b

    if not args.no_torch:
        import torch

        from mccnn_cl.reference.network import cost_volume_torch
        from mccnn_cl.train.model import MCCNN
        model = MCCNN.from_weights(w).eval()
        cost_volume_torch(w, left[:64, :128], right[:64, :128], 4, model=model)  # warm-up
        t0 = time.perf_counter()
        vol_t = cost_volume_torch(w, left, right, D, model=model)
        t_torch = time.perf_counter() - t0
        vol_cl = ctx.from_device(d_cost, (D, H - 8, W - 8))
        err = np.nanmax(np.abs(vol_cl - vol_t))
        same_nan = np.array_equal(np.isnan(vol_cl), np.isnan(vol_t))
        print(f"torch {torch.__version__} ({torch.get_num_threads()} threads): {t_torch:.2f} s = "
              f"{total_flop / t_torch / 1e9:.1f} GFLOP/s; max |OpenCL - torch| = {err:.2e}, "
              f"NaN positions {'equal' if same_nan else 'DIFFER'}")
        print(f"ratio OpenCL/torch speed: {t_torch / t_cl:.2f}x")
    rate_cl = total_flop / t_cl / 1e9
    print(f"ratio OpenCL/numpy GEMM rate: {rate_cl / np_rate:.2f} (head alone "
          f"{head_flop / t_head / 1e9 / np_rate:.2f})")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
