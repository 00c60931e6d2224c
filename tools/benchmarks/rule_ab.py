"""One kernel rule's values A/B through the whole stereo method, in turn in one
process, on KITTI 2015 000000 (BENCHMARKS.md): each value gets its own context
whose device profile has the rule set (as a tuned choice would), each round
runs every value once, and the per-stage groups (cost, CBCA, SGM, the rest)
and whole calls are printed per value, with the disparity maps compared.

    .venv/bin/python tools/benchmarks/rule_ab.py sgm_width 16 8 [--weights general-fst] [--cost cnn|census]
        [--data ../shared/data] [--rounds 5]

Values are parsed as JSON where they parse (16, true, [64, 2, 2]), else kept
as strings.  Speed drifts between minutes: only the ratios within a round mean
much; pause other work on the machine.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from mccnn_cl import StereoMatcher
from mccnn_cl.benchmark import GROUPS, group_timings
from mccnn_cl.opencl.context import ClContext
from mccnn_cl.opencl.device import RULES

from _paths import data_dir  # noqa: E402


def _value(text: str):
    try:
        return json.loads(text)
    except ValueError:
        return text


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("rule", choices=sorted(RULES))
    ap.add_argument("values", nargs="+", type=_value)
    ap.add_argument("--weights", default="general-fst")
    ap.add_argument("--cost", choices=("cnn", "census"), default="cnn")
    ap.add_argument("--data", default=str(data_dir()), help="shared data (default: $MCCNN_DATA, else ../shared/data)")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    k = Path(args.data) / "kitti2015" / "training"
    L, R = (cv2.imread(str(k / d / "000000_10.png"), cv2.IMREAD_GRAYSCALE) for d in ("image_2", "image_3"))
    if L is None or R is None:
        raise SystemExit(f"no KITTI 2015 pair 000000 under {k}")
    matchers, maps = {}, {}
    for v in args.values:
        ctx = ClContext()
        ctx.profile.tuned[args.rule] = v
        kw = dict(cost="census") if args.cost == "census" else dict(weights=args.weights)
        matchers[str(v)] = m = StereoMatcher(max_disparity=228, device=ctx, **kw)
        maps[str(v)] = m.compute(L, R)  # warm-up: builds, first touch (the disparity map)
    print(f"device: {ctx.describe()}; rule {args.rule}, values {args.values}, {args.rounds} rounds")
    first = next(iter(maps.values()))
    for name, d in maps.items():
        same = np.array_equal(d, first, equal_nan=True)
        print(f"  {args.rule}={name}: disparity map {'the same as' if same else 'DIFFERS from'} the first value's")
    rows = {name: [] for name in matchers}
    for r in range(args.rounds):
        order = list(matchers) if r % 2 == 0 else list(reversed(matchers))
        for name in order:
            t = time.perf_counter()
            res = matchers[name].compute(L, R, timings=True)
            wall = time.perf_counter() - t
            g = group_timings(res.timings)
            rows[name].append((wall, g))
            print(f"round {r}: {args.rule}={name}: whole call {wall:.3f} s | "
                  + " ".join(f"{k} {g.get(k, 0.0):.3f}" for k in GROUPS), flush=True)
    for name, runs in rows.items():
        walls = sorted(w for w, _ in runs)
        med = {k: float(np.median([g.get(k, 0.0) for _, g in runs])) for k in GROUPS}
        print(f"{args.rule}={name}: whole call median {np.median(walls):.3f} s (best {walls[0]:.3f}) | medians "
              + " ".join(f"{k} {med[k]:.3f}" for k in GROUPS))


if __name__ == "__main__":
    main()
