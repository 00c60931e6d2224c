"""Sparsification curves of the confidence (StereoMatcher.compute(..., confidence=True)).

    .venv/bin/python tools/benchmarks/sparsification.py                 # ~2 min on 2 CPU cores
    .venv/bin/python tools/benchmarks/sparsification.py --plot docs/img/sparsification.png --json out.json
    .venv/bin/python tools/benchmarks/sparsification.py --render DIR SCENE_DIR ...   # confidence pictures of unlabeled pairs

Runs on the project's held-out pairs: KITTI 2015 000000 with the census cost
(D = 228, 3-px error) and Middlebury Cones (quarter size, ndisp, bad-2.0)
with census and with the shipped network.  For each, the error of the final
disparity on the pixels kept as the lowest-confidence fraction is dropped
(0 .. 90 %), beside the oracle that drops by true error
(:func:`mccnn_cl.evaluation.metrics.sparsification`), on non-occluded and on all GT.
``--render`` writes, per scene folder holding im0.png/im1.png, the left
image, the disparity and the confidence side by side (census, D = 64).
Data: ``../shared/data`` or ``$MCCNN_DATA``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from mccnn_cl.opencl.context import ClContext
from mccnn_cl.evaluation.datasets import load_kitti2015, load_middlebury
from mccnn_cl.evaluation.metrics import sparsification
from mccnn_cl.pipeline import StereoMatcher
from mccnn_cl.visualize import colorize, label

from _paths import data_dir  # noqa: E402

DATA = data_dir()

RUNS = (("KITTI 2015 000000, census (3-px)", "kitti", "census"),
        ("Cones, census (bad-2.0)", "cones", "census"),
        ("Cones, shipped network (bad-2.0)", "cones", "cnn"))


def load(which):
    if which == "kitti":
        return load_kitti2015(DATA / "kitti2015" / "training", "000000"), 228, 3.0
    pair = load_middlebury(DATA / "middlebury" / "Cones")
    return pair, pair.ndisp or 64, 2.0


def evaluate(ctx):
    results = []
    for title, which, cost in RUNS:
        pair, D, thr = load(which)
        t0 = time.perf_counter()
        res = StereoMatcher(cost=cost, max_disparity=D, device=ctx).compute(pair.left, pair.right, confidence=True)
        seconds = time.perf_counter() - t0
        row = {"run": title, "seconds": round(seconds, 1), "threshold": thr,
               "correct_labels": float(np.mean(res.labels == 0))}
        for name, mask in (("noc", pair.valid_noc), ("all", pair.valid_all)):
            s = sparsification(res.disparity, pair.disp, res.confidence, thr, mask)
            row[name] = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in s.items()}
        results.append(row)
        print(f"{title}: {seconds:.0f} s; correct labels {row['correct_labels']:.1%}")
        for name in ("noc", "all"):
            r = row[name]
            print(f"  {name}: error {r['curve'][0]:.2f} %, at 50 % dropped {r['curve'][10]:.2f} % "
                  f"(oracle {r['oracle'][10]:.2f}), AUC {r['auc']:.2f} (oracle {r['oracle_auc']:.2f})")
    return results


def plot(results, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(4.2 * len(results), 3.6), constrained_layout=True)
    for ax, row in zip(axes, results):
        for name, style in (("noc", "-"), ("all", "--")):
            r = row[name]
            f = 100 * np.asarray(r["fractions"])
            ax.plot(f, r["curve"], "C0" + style, label=f"confidence, {name} (AUC {r['auc']:.2f})")
            ax.plot(f, r["oracle"], "C3" + style, label=f"oracle, {name} (AUC {r['oracle_auc']:.2f})")
        ax.set_title(row["run"], fontsize=10)
        ax.set_xlabel("pixels dropped, lowest confidence first [%]")
        ax.set_ylabel("error of the kept pixels [%]")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.savefig(path, dpi=110)


def render(ctx, out_dir, scenes, D=64):
    """Left image | disparity | confidence (gray, black = 0) of each scene, one PNG each."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    m = StereoMatcher(cost="census", max_disparity=D, device=ctx)
    for scene in scenes:
        scene = Path(scene)
        left = cv2.imread(str(scene / "im0.png"))
        right = cv2.imread(str(scene / "im1.png"))
        res = m.compute(left, right, confidence=True)
        gray = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)
        conf = cv2.cvtColor(np.round(255 * res.confidence).astype(np.uint8), cv2.COLOR_GRAY2BGR)
        panels = [label(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR), "left"),
                  label(colorize(res.disparity, 0, D - 1), f"disparity (census, D={D})"),
                  label(conf, f"confidence (0 black .. 1 white), {np.mean(res.labels == 0):.0%} correct")]
        name = out_dir / f"{scene.parent.name}_{scene.name}.png"
        cv2.imwrite(str(name), np.hstack(panels))
        print(f"{name}: mean confidence {res.confidence.mean():.2f}, correct labels {np.mean(res.labels == 0):.1%}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--plot", metavar="PNG", help="write the curves here")
    ap.add_argument("--json", metavar="FILE", help="write the curves as JSON")
    ap.add_argument("--render", nargs="+", metavar=("DIR", "SCENE"), help="render unlabeled scenes instead")
    args = ap.parse_args(argv)
    ctx = ClContext(args.device)
    if args.render:
        return render(ctx, args.render[0], args.render[1:])
    results = evaluate(ctx)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    if args.plot:
        plot(results, args.plot)


if __name__ == "__main__":
    main()
