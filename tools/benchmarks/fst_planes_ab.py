"""The fst network stage with its normalised features' buffers kept between
calls (the default) against fresh ones each call (the pool emptied before the
call), A/B in turn in one process, on KITTI 2015 000000 (BENCHMARKS.md).

    .venv/bin/python tools/benchmarks/fst_planes_ab.py [--weights general-fst] [--data ../shared/data] [--rounds 5]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2

from mccnn_cl import StereoMatcher
from mccnn_cl.opencl.context import ClContext

from _paths import data_dir  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--weights", default="general-fst")
    ap.add_argument("--data", default=str(data_dir()), help="shared data (default: $MCCNN_DATA, else ../shared/data)")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    k = Path(args.data) / "kitti2015" / "training"
    L, R = (cv2.imread(str(k / d / "000000_10.png"), cv2.IMREAD_GRAYSCALE) for d in ("image_2", "image_3"))
    m = StereoMatcher(weights=args.weights, max_disparity=228, device=ClContext())
    m.compute(L, R)  # warm-up: builds, first touch
    cnn = {"fresh": [], "kept": []}
    total = {"fresh": [], "kept": []}
    for _ in range(args.rounds):
        for mode in ("fresh", "kept"):
            if mode == "fresh":
                m.cost._planes.clear()
            t = time.perf_counter()
            res = m.compute(L, R, timings=True)
            total[mode].append(time.perf_counter() - t)
            cnn[mode].append(res.timings["C_CNN"])
    for mode in cnn:
        print(f"{mode}: network {' '.join(f'{v:.3f}' for v in cnn[mode])} s | "
              f"whole call {' '.join(f'{v:.3f}' for v in total[mode])} s")


if __name__ == "__main__":
    main()
