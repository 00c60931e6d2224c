"""Time the confidence stage on a KITTI-size volume beside the device's copy bandwidth.

    python tools/benchmarks/bench_confidence.py [--repeat 5]

The confidence reads the final volume once (D x H x W float32) and writes one
float per pixel, so its floor is one read of the volume at the device's copy
rate, in bench's convention (mccnn_cl.benchmark.traffic_floor): the bytes a
stage moves, reads + writes, over the copy rate, which counts a copy's read
and its write; one read of V bytes costs V / rate, half a copy's time.
The volume is census's of KITTI 2015 000000 (D = 228) from the shared data
($MCCNN_DATA, default ../shared/data beside the repository).
"""

import argparse
import os
import time

import numpy as np

from _paths import data_dir  # noqa: E402

from mccnn_cl.benchmark import copy_baseline, traffic_floor
from mccnn_cl.opencl.context import ClContext
from mccnn_cl.evaluation.datasets import discover
from mccnn_cl.imageops import to_gray
from mccnn_cl.costs.census import CensusCost
from mccnn_cl.stages.confidence import Confidence

DATA = str(data_dir())


def read_floor(volume_bytes, copy_bw) -> float:
    """Seconds of one read of the volume at the copy rate (bench's convention:
    ``copy_bw`` counts read + write, a read of V bytes moves V)."""
    return traffic_floor(volume_bytes, copy_bw)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    ctx = ClContext()
    pair = [r for r in discover(DATA, labeled=True) if r.key == "kitti2015/000000"][0].load()
    L, R = to_gray(pair.left), to_gray(pair.right)
    D = 228
    cost = CensusCost(ctx)
    d_vol = cost(L, R, D)
    H, W = L.shape[0] - 2 * cost.margin, L.shape[1] - 2 * cost.margin
    labels = ctx.to_device(np.zeros((H, W), np.int32))  # all "correct": every curve is measured
    conf = Confidence(ctx)
    out = conf(d_vol, labels, D, H, W, cost.floor)
    ctx.finish()
    best = float("inf")
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        conf(d_vol, labels, D, H, W, cost.floor, out=out)
        ctx.finish()
        best = min(best, time.perf_counter() - t0)
    base = copy_baseline(ctx)
    bw = base["rate"]
    floor_s = read_floor(D * H * W * 4, bw)
    print(f"device: {ctx.describe()}; {os.cpu_count()} cores, load average (1 min) {os.getloadavg()[0]:.2f}")
    print(f"volume {D} x {H} x {W} float32 ({D * H * W * 4 / 2**20:.0f} MiB); copy {bw / 1e9:.1f} GB/s "
          f"(read + write counted, {base['nbytes'] / 2**20:.0f} MiB, best of {base['repeat']}, {base['timer']})")
    print(f"confidence: {best * 1e3:.0f} ms (best of {args.repeat}); floor, one read of the volume (V bytes) "
          f"at that rate (bench's convention: bytes read + written / copy rate) {floor_s * 1e3:.0f} ms; "
          f"ratio {best / floor_s:.2f}x")


if __name__ == "__main__":
    main()
