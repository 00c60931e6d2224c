"""Does a volume row pitch that is a multiple of 16 floats speed up the pipeline?
The volumes' row pitch is the image width W, so the KITTI 2015 pair 000000 cropped
to widths around 1242 (a multiple of 16, of 8, neither) gives the answer without
changing a kernel: every width runs in one process, in turn (forward, then
backward), and the median per stage group is printed (BENCHMARKS.md, "Machine C,
a twelfth session").

    .venv/bin/python tools/benchmarks/width_ab.py [--weights kitti-fst | --cost census] [--widths 1232,1234,1240,1239] [--rounds 6] [--set sgm_int16=true]

The widths differ by < 1 % in work, far below the host's drift between minutes,
so only the per-stage medians of one run compare.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from _paths import kitti_000000


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default="kitti-fst")
    ap.add_argument("--cost", choices=("cnn", "census"), default="cnn")
    ap.add_argument("--widths", default="1232,1234,1240,1239")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a hyperparameter (true/false or a number), e.g. sgm_int16=true")
    ap.add_argument("--data", default=None, help="shared data (default: $MCCNN_DATA, else ../shared/data)")
    args = ap.parse_args()
    from mccnn_cl.benchmark import group_timings
    from mccnn_cl.hyperparameters import parse_settings
    from mccnn_cl.pipeline import StereoMatcher

    pair = kitti_000000(args.data)
    L, R = pair.left, pair.right
    widths = [int(w) for w in args.widths.split(",")]
    if max(widths) > L.shape[1]:
        sys.exit(f"widths up to {L.shape[1]}")
    hp = parse_settings(args.set)
    m = StereoMatcher(cost="census", **hp) if args.cost == "census" else StereoMatcher(weights=args.weights, **hp)
    crops = {w: (np.ascontiguousarray(L[:, :w]), np.ascontiguousarray(R[:, :w])) for w in widths}
    for w in widths:  # programs and buffers of every width made before timing
        m.compute(*crops[w])
    res = {w: [] for w in widths}
    for r in range(args.rounds):
        for w in (widths if r % 2 == 0 else widths[::-1]):
            res[w].append(group_timings(m.compute(*crops[w], timings=True).timings))
    groups = list(res[widths[0]][0])
    print(f"{m.ctx.describe()}, {args.cost if args.cost == 'census' else args.weights}, {hp or 'defaults'}\n"
          "| W | row bytes mod 64 | "
          + " | ".join(groups) + " | total |")
    print("|---" * (len(groups) + 3) + "|")
    for w in widths:
        med = {g: float(np.median([x[g] for x in res[w]])) for g in groups}
        tot = float(np.median([sum(x.values()) for x in res[w]]))
        print(f"| {w} | {4 * w % 64} | " + " | ".join(f"{1000 * med[g]:.1f} ms" for g in groups)
              + f" | {1000 * tot:.1f} ms |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
