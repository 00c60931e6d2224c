"""Per-stage runtime of the stereo method on a KITTI-size pair, in the layout of
the paper's runtime table (CNN / SGM / CBCA / everything else), beside OpenCV
StereoSGBM on the same pair.

    python tools/benchmarks/bench_pipeline.py
    python tools/benchmarks/bench_pipeline.py --cnn-disp 4 --repeat 2 --device cpu

The pair is KITTI 2015 training 000000 (image_2 / image_3, 1242 x 375),
cropped to 1240 columns and padded to 376 rows (last row repeated): the
paper's 1240 x 376, with 228 disparity levels.  The stereo stages (CBCA, SGM,
WTA, ..., bilateral) run on the census cost volume.  The network's time is
measured separately with paper-sized weights (the shipped model if present,
else random weights of the paper's architecture: the runtime does not depend
on the values) for ``--cnn-disp`` disparities only when that is fewer than
228, and extrapolated linearly to 228 from two measurements (1 and N
disparities: fixed L1-L3 cost + per-disparity head cost); the output says so.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import cv2
import numpy as np

from _paths import data_dir  # noqa: E402
DATA = data_dir()

# Groups of mccnn_cl.benchmark.STAGE_GROUP (the one stage-name table) -> rows of the paper's table.
ROWS = {"cost": "matching cost", "CBCA": "CBCA", "SGM": "SGM", "rest": "everything else"}


def kitti_pair(height=376, width=1240):
    d = DATA / "kitti2015" / "training"
    left = cv2.imread(str(d / "image_2" / "000000_10.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(d / "image_3" / "000000_10.png"), cv2.IMREAD_GRAYSCALE)
    if left is None or right is None:
        sys.exit(f"KITTI 2015 000000 not found under {d}")

    def fit(img):
        img = img[:height, :width]
        return cv2.copyMakeBorder(img, 0, height - img.shape[0], 0, width - img.shape[1], cv2.BORDER_REPLICATE)

    return fit(left), fit(right)


def time_cnn(ctx, left, right, ndisp, repeat):
    """(seconds for 228 disparities, how it was obtained, weights description)."""
    from mccnn_cl.pipeline import to_gray
    from mccnn_cl.costs.network import NetworkCost
    from mccnn_cl.weights import Weights, default_weights_path, shipped_models

    if os.path.exists(default_weights_path()):
        weights, what = Weights.load(shipped_models()["kitti-paper"]), "shipped paper weights (kitti-paper)"
    else:
        weights, what = Weights.random(seed=0), "random weights, paper architecture"
    net = NetworkCost(ctx, weights)
    gl, gr = to_gray(left, "left"), to_gray(right, "right")

    def run(n):
        best = np.inf
        for _ in range(repeat):
            t0 = time.perf_counter()
            d = net(gl, gr, n)
            ctx.finish()
            best = min(best, time.perf_counter() - t0)
            d.release()
        return best

    run(1)  # build + first-launch compilation
    if ndisp >= 228:
        return run(228), "measured, 228 disparities", what
    t1, tn = run(1), run(ndisp)
    per = (tn - t1) / max(ndisp - 1, 1)
    est = t1 + 227 * per
    return est, (f"extrapolated: {t1:.2f} s at 1 disparity, {tn:.2f} s at {ndisp}, "
                 f"{per:.3f} s per extra disparity"), what


def accuracy(ctx):
    """Error rates of the census pipeline, census WTA (same cost, border copied)
    and OpenCV SGBM (holes counted as errors, and filled as the KITTI devkit
    does) on the KITTI 2015 pair (bad-3, non-occluded GT) and the Middlebury
    scenes with a non-occlusion mask (bad-2, non-occluded GT, ndisp levels)."""
    from mccnn_cl.evaluation.baseline import sgbm
    from mccnn_cl.io import read_kitti_disparity, read_pfm
    from mccnn_cl.evaluation.metrics import bad_pixel_rate, fill_invalid
    from mccnn_cl.pipeline import StereoMatcher, to_gray
    from mccnn_cl.reference.disparity import enlarge
    from mccnn_cl.costs.census import CensusCost
    from mccnn_cl.stages.disparity import WinnerTakeAll

    cases = []
    k = DATA / "kitti2015" / "training"
    gt, valid = read_kitti_disparity(k / "disp_noc_0" / "000000_10.png")
    gt[~valid] = np.nan
    cases.append(("KITTI 2015 000000", cv2.imread(str(k / "image_2" / "000000_10.png")),
                  cv2.imread(str(k / "image_3" / "000000_10.png")), gt, None, 228, 3.0))
    for scene in ("Tsukuba", "Venus", "Cones"):
        d = DATA / "middlebury" / scene
        ndisp = int([ln for ln in open(d / "calib.txt") if ln.startswith("ndisp")][0].split("=")[1])
        mask = cv2.imread(str(d / "mask0nocc.png"), cv2.IMREAD_GRAYSCALE) == 255
        cases.append((f"Middlebury {scene}", cv2.imread(str(d / "im0.png")), cv2.imread(str(d / "im1.png")),
                      read_pfm(d / "disp0GT.pfm"), mask, ndisp, 2.0))
    rows = []
    for name, left, right, gt, mask, D, thr in cases:
        disp = StereoMatcher(cost="census", max_disparity=D, device=ctx).compute(left, right)
        gl, gr = to_gray(left, "left"), to_gray(right, "right")
        H, W = gl.shape[0] - 8, gl.shape[1] - 8
        wta = ctx.from_device(WinnerTakeAll(ctx).left(CensusCost(ctx)(gl, gr, D), D, H, W), (H, W), np.int32)
        wta = enlarge(wta.astype(np.float32), 4, gl.shape)
        lg = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)
        rg = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)
        sg = sgbm(lg, rg, D)
        rates = [bad_pixel_rate(x, gt, thr, mask) for x in (disp, wta, sg, fill_invalid(sg))]
        rows.append((name, thr, D, *rates))
    print(f"\n| pair (non-occluded GT) | bad-T | D | census pipeline | census WTA | SGBM (holes = errors) "
          "| SGBM (holes filled) |")
    print("|---|---|---|---|---|---|---|")
    for name, thr, D, a, b, c, e in rows:
        print(f"| {name} | {thr:g} px | {D} | {a:.2f} % | {b:.2f} % | {c:.2f} % | {e:.2f} % |")
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None, help="OpenCL device spec (see mccnn_cl.opencl.context.select_device)")
    ap.add_argument("--max-disparity", type=int, default=228)
    ap.add_argument("--repeat", type=int, default=1, help="timed runs after the warm-up; best is kept")
    ap.add_argument("--cnn-disp", type=int, default=4,
                    help="disparities to run the network for (extrapolated to 228 when fewer); 0 = skip")
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    ap.add_argument("--accuracy", action="store_true",
                    help="only print error rates on KITTI 2015 000000 and Middlebury Tsukuba/Venus/Cones")
    args = ap.parse_args(argv)
    if args.accuracy:
        from mccnn_cl.opencl.context import ClContext

        accuracy(ClContext(args.device))
        return

    from mccnn_cl.evaluation.baseline import sgbm
    from mccnn_cl.opencl.context import ClContext
    from mccnn_cl.pipeline import StereoMatcher

    ctx = ClContext(args.device)
    left, right = kitti_pair()
    D = args.max_disparity
    print(f"device: {ctx.describe()}")
    print(f"pair: KITTI 2015 000000 fitted to {left.shape[1]} x {left.shape[0]}, {D} disparities")

    matcher = StereoMatcher(cost="census", max_disparity=D, device=ctx)
    matcher.compute(left, right, timings=True)  # warm-up: first launches compile on some runtimes
    best = None
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        res = matcher.compute(left, right, timings=True)
        total = time.perf_counter() - t0
        if best is None or total < best[0]:
            best = (total, res.timings)
    total, stages = best

    from mccnn_cl.benchmark import group_timings

    groups = {ROWS[g]: t for g, t in group_timings(stages).items()}
    groups["everything else"] += total - sum(stages.values())  # uploads, the final copy

    cnn = None
    if args.cnn_disp > 0:
        try:
            import mccnn_cl.costs.network  # noqa: F401
        except ImportError:
            print("network stage not available: CNN time not measured")
        else:
            cnn = time_cnn(ctx, left, right, args.cnn_disp, max(1, args.repeat))

    _, t_sgbm = sgbm(left, right, D, return_time=True)  # first call, then the timed one
    t_sgbm = min(sgbm(left, right, D, return_time=True)[1] for _ in range(max(1, args.repeat)))

    print("\n| Component | Runtime | paper (GTX Titan) |")
    print("|---|---|---|")
    if cnn is not None:
        print(f"| Convolutional neural network | {cnn[0]:.1f} s ({cnn[1]}; {cnn[2]}) | 95 s |")
    print(f"| Census cost (used for the rows below) | {groups['matching cost']:.2f} s | - |")
    both = " (left and right reference)" if matcher.params.right_reference == "aggregated" else ""
    print(f"| Semiglobal matching{both} | {groups['SGM']:.2f} s | 3 s |")
    print(f"| Cross-based cost aggregation{both}: arms + 2 x 4 iterations | {groups['CBCA']:.2f} s | 2 s |")
    print(f"| Everything else | {groups['everything else']:.2f} s | 0.03 s |")
    print(f"| Total, census cost | {total:.2f} s | - |")
    if cnn is not None:
        print(f"| Total with the CNN | {total - groups['matching cost'] + cnn[0]:.1f} s | 100 s |")
    print(f"| OpenCV StereoSGBM (3-way, 240 levels, CPU) | {t_sgbm:.2f} s | - |")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"\n{os.cpu_count()} CPU cores, load average {load:.1f} at the end of the run")
    print("\nper stage (s): " + ", ".join(f"{k} {v:.3f}" for k, v in stages.items()))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": ctx.describe(), "stages": stages, "groups": groups, "total": total,
                       "cnn": cnn, "sgbm": t_sgbm, "max_disparity": D}, f, indent=1)


if __name__ == "__main__":
    main()
