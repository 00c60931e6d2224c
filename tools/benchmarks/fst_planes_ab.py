"""The fst network stage with its normalised features' buffers kept between
calls (the default) against fresh ones each call (the pool emptied before the
call), A/B in turn in one process, on KITTI 2015 000000 (BENCHMARKS.md).

    .venv/bin/python tools/benchmarks/fst_planes_ab.py [WEIGHTS (default general-fst)] [--data DIR]
"""
import os
import sys
import time

import cv2

from mccnn_cl.io import read_image
from mccnn_cl import StereoMatcher
from mccnn_cl.opencl.context import ClContext
DATA = sys.argv[sys.argv.index("--data") + 1] if "--data" in sys.argv else \
    os.path.join(os.path.dirname(__file__), "..", "..", "..", "shared", "data")
K = os.path.join(DATA, "kitti2015", "training")


def g(p):
    return cv2.cvtColor(read_image(p), cv2.COLOR_RGB2GRAY)


L, R = g(f"{K}/image_2/000000_10.png"), g(f"{K}/image_3/000000_10.png")
ctx = ClContext()
weights = sys.argv[1] if len(sys.argv) > 1 and not sys.argv[1].startswith("--") else "general-fst"
m = StereoMatcher(weights=weights, max_disparity=228, device=ctx)
m.compute(L, R)
res = {"fresh": [], "kept": []}
tot = {"fresh": [], "kept": []}
for r in range(5):
    for mode in ("fresh", "kept"):
        if mode == "fresh":
            m.cost._planes.clear()
        t = time.perf_counter()
        out = m.compute(L, R, timings=True)
        tt = time.perf_counter() - t
        res[mode].append(out.timings["C_CNN"]); tot[mode].append(tt)
for mode in res:
    print(mode, "C_CNN", " ".join(f"{v:.3f}" for v in res[mode]), "| total", " ".join(f"{v:.3f}" for v in tot[mode]))
