"""A/B of the conv register tile (CONV_RM pixels per work-item) in one process.

    python tools/benchmarks/conv_tiles.py [--rm 4 6 8] [--rounds 3] [--weights NAME]

Builds one StereoMatcher per CONV_RM value (the profile's ``network_tiles``
row set for each, everything else the rules'), then times the matching-cost
stage (C_CNN: conv stack on both images + the volume) of each on the
synthetic 1242 x 375 pair at D 228, in interleaved rounds (the order reversed
every other round), and prints each value's best and every time. All
matchers' disparity maps must be identical (the kernels do the same float
operations in the same order whatever the tile); the script says so or fails.
Run it with ``POCL_KERNELLIB_NAME=avx2`` to see PoCL's AVX2 code on an
AVX-512 machine (docs/tuning.md).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", ".."))

from mccnn_cl.benchmark import synthetic_pair  # noqa: E402
from mccnn_cl.opencl.context import ClContext  # noqa: E402
from mccnn_cl.pipeline import StereoMatcher  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rm", type=int, nargs="+", default=[4, 6, 8], help="CONV_RM values (default 4 6 8)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--weights", default=None, help="network (default: the package's default)")
    args = ap.parse_args(argv)
    ctx = ClContext(None)
    print(f"device: {ctx.device.name}; other choices: {ctx.profile.tuned or 'the rules table'}")
    left, right = synthetic_pair(1242, 375, 228)
    base = ctx.profile.network_tiles()
    runs = []
    for rm in args.rm:
        ctx.profile.tuned["network_tiles"] = dict(base, CONV_RM=int(rm))
        m = StereoMatcher(args.weights, max_disparity=228, device=ctx)
        runs.append((rm, m, m.compute(left, right)))  # warm-up: programs built, buffers touched
    ref = runs[0][2]
    for rm, _, disp in runs[1:]:
        if not np.array_equal(disp, ref, equal_nan=True):
            print(f"CONV_RM={rm}: disparity map differs from CONV_RM={runs[0][0]}'s")
            return 1
    times = {rm: [] for rm, _, _ in runs}
    for r in range(args.rounds):
        for rm, m, _ in (runs if r % 2 == 0 else runs[::-1]):
            times[rm].append(m.compute(left, right, timings=True).timings["C_CNN"])
    print("maps identical for every CONV_RM")
    for rm, ts in times.items():
        print(f"CONV_RM={rm:<3} C_CNN best {min(ts):.3f} s   all {' '.join(f'{t:.3f}' for t in ts)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
