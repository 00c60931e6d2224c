"""SGM in float against SGM in 16-bit lanes (the ``sgm_int16`` hyperparameter) on a
pipeline's real volume, in one process: the matcher runs once on a KITTI pair to get
the volume SGM reads (C_CBCA), then the device's SGM stage is called on it without and
with ``cost_bound``, alternating which goes first, best of 3 calls per round
(BENCHMARKS.md, "SGM in 16-bit lanes").

    .venv/bin/python tools/benchmarks/sgm_int16_ab.py [--weights general-fst | --cost census] [--rounds 12]

Separate ``mccnn-cl bench`` processes do not measure this: on these VMs the second of
two processes run back to back was the faster in 7 of 7 pairs, whichever setting it had.
One SGM call is one reference's (the pipeline makes two).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default="general-fst", help="network (default: general-fst)")
    ap.add_argument("--cost", choices=("cnn", "census"), default="cnn")
    ap.add_argument("--rounds", type=int, default=12)
    ap.add_argument("--pair", default=None, help="left image of a pair (default: KITTI 2015 training 000000 "
                                                 "under MCCNN_DATA or ../shared/data)")
    args = ap.parse_args()
    import cv2

    from mccnn_cl.pipeline import StereoMatcher

    from _paths import data_dir

    data = data_dir()
    left = Path(args.pair) if args.pair else data / "kitti2015" / "training" / "image_2" / "000000_10.png"
    right = Path(str(left).replace("image_2", "image_3"))
    L, R = cv2.imread(str(left)), cv2.imread(str(right))
    if L is None or R is None:
        sys.exit(f"cannot read {left} and {right}: set MCCNN_DATA or --pair")
    m = StereoMatcher(cost="census") if args.cost == "census" else StereoMatcher(weights=args.weights)
    C = np.ascontiguousarray(m.compute(L, R, return_intermediates=True).intermediates["C_CBCA"], dtype=np.float32)
    D, H, W = C.shape
    ctx, p, stage = m.ctx, m.params, m.sgm
    bound = m.cost.magnitude_bound()
    if bound is None or not getattr(stage, "int16", False):
        sys.exit(f"no 16-bit SGM here: stage {type(stage).__name__}, cost bound {bound}")
    rng = np.random.default_rng(0)  # timing only: the gradients' images need not be the pair's
    d_l, d_r = (ctx.to_device(rng.random((H, W), dtype=np.float32)) for _ in range(2))
    d_c, d_out = ctx.to_device(C), ctx.empty(C.nbytes, "SGM output")
    pen = (p.sgm_pi1, p.sgm_pi2, p.sgm_tau_so, p.sgm_q1, p.sgm_q2, p.sgm_v, p.sgm_variant, p.sgm_p2_times_pi1,
           p.sgm_outside_large)

    def run(b):
        t = time.perf_counter()
        stage(d_c, d_l, d_r, D, H, W, *pen, out=d_out, cost_bound=b)
        ctx.queue.finish()
        return time.perf_counter() - t

    run(None), run(bound)
    scale = stage.last_scale
    times = {"float": [], "16-bit": []}
    for r in range(args.rounds):
        order = (("float", None), ("16-bit", bound)) if r % 2 == 0 else (("16-bit", bound), ("float", None))
        for name, b in order:
            times[name].append(min(run(b) for _ in range(3)))
    f, q = np.array(times["float"]), np.array(times["16-bit"])
    print(f"device: {ctx.describe()}")
    print(f"{args.cost if args.cost == 'census' else args.weights}: D {D}, {H} x {W}, bound {bound:g}, "
          f"scale {scale:g}")
    print(f"float median {1e3 * np.median(f):.1f} ms, 16-bit median {1e3 * np.median(q):.1f} ms: "
          f"{np.median(q) / np.median(f):.3f}x, 16-bit faster in {int((q < f).sum())} of {len(f)} rounds")
    for name, v in (("float", f), ("16-bit", q)):
        print(f"  {name}: " + " ".join(f"{1e3 * t:.0f}" for t in v))
    return 0


if __name__ == "__main__":
    sys.exit(main())
