"""A/B of a network register tile (CONV_RM pixels per conv work-item, or RM
cells per head work-item) in one process.

    python tools/benchmarks/conv_tiles.py [--key CONV_RM] [--values 4 6 8] [--rounds 3]
                                          [--weights NAME] [--size 1242x375] [--disp 228]

Builds one StereoMatcher per value (the profile's ``network_tiles`` row with
that key set, everything else the rules'), then times the matching-cost stage
(C_CNN: conv stack on both images + the volume or the head) of each on the
synthetic pair, in interleaved rounds (the order reversed every other round),
and prints each value's best and every time. All matchers' disparity maps
must be identical (the kernels do the same float operations in the same order
whatever the tile); the script says so or fails.
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
from mccnn_cl.cli.common import parse_size  # noqa: E402
from mccnn_cl.opencl.context import ClContext  # noqa: E402
from mccnn_cl.pipeline import StereoMatcher  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--key", default="CONV_RM", choices=["CONV_RM", "RM"], help="the tile size varied")
    ap.add_argument("--values", type=int, nargs="+", default=[4, 6, 8], help="its values (default 4 6 8)")
    ap.add_argument("--size", default="1242x375", help="synthetic pair, WIDTHxHEIGHT")
    ap.add_argument("--disp", type=int, default=228)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--weights", default=None, help="network (default: the package's default)")
    args = ap.parse_args(argv)
    ctx = ClContext(None)
    print(f"device: {ctx.device.name}; other choices: {ctx.profile.tuned or 'the rules table'}")
    w, h = parse_size(args.size, 2, "1242x375", what="width x height")
    left, right = synthetic_pair(w, h, args.disp)
    others = dict(ctx.profile.tuned.get("network_tiles", {}))  # sizes tuned on this device stay
    runs = []
    for rm in args.values:
        ctx.profile.tuned["network_tiles"] = {**others, args.key: int(rm)}  # over the rules' row
        m = StereoMatcher(args.weights, max_disparity=args.disp, device=ctx)
        runs.append((rm, m, m.compute(left, right)))  # warm-up: programs built, buffers touched
    ref = runs[0][2]
    for rm, _, disp in runs[1:]:
        if not np.array_equal(disp, ref, equal_nan=True):
            print(f"{args.key}={rm}: disparity map differs from {args.key}={runs[0][0]}'s")
            return 1
    times = {rm: [] for rm, _, _ in runs}
    for r in range(args.rounds):
        for rm, m, _ in (runs if r % 2 == 0 else runs[::-1]):
            times[rm].append(m.compute(left, right, timings=True).timings["C_CNN"])
    print(f"maps identical for every {args.key}")
    for rm, ts in times.items():
        print(f"{args.key}={rm:<3} C_CNN best {min(ts):.3f} s   all {' '.join(f'{t:.3f}' for t in ts)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
