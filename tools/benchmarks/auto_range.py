"""The automatic disparity range against the stated one on the shared pairs
(docs/method.md, "Disparity ranges"): per pair the error of both, their wall
and CPU seconds (time.process_time: PoCL's threads included), the coarse
pass's seconds and the fraction of ground-truth pixels outside the chosen
range, one JSON row per pair on stdout and all of them in OUT.json.

    MEM_GIB=2 python bench/auto_range.py census|WEIGHTS OUT.json [family,...]

Families: kitti2012, kitti2015, middlebury, middeval3, eth3d (ETH3D read
from two_view_training/<scene> and two_view_training_gt/<scene>, its ndisp
capped at the width less one); EVERY=N takes every Nth pair.  Data: the
shared folder (MCCNN_SHARED_DATA, default ../shared/data)."""
import json, os, sys, time
from pathlib import Path
import numpy as np
from mccnn_cl import StereoMatcher
from mccnn_cl.opencl.context import ClContext
from mccnn_cl.evaluation.datasets import discover, to_gray_u8 as to_gray, load_middlebury
from mccnn_cl.evaluation.scoring import default_range
from mccnn_cl.io import read_image, read_pfm
from mccnn_cl.evaluation import metrics

SD = Path(os.environ.get("MCCNN_SHARED_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"))
cost = sys.argv[1]
out_path = sys.argv[2]
only = sys.argv[3].split(",") if len(sys.argv) > 3 else None
ctx = ClContext(None)
kw = dict(cost="census") if cost == "census" else dict(weights=cost)
import os
kw["memory_limit"] = int(float(os.environ.get("MEM_GIB", "2")) * 2**30)  # the same for both runs
step = int(os.environ.get("EVERY", "1"))
pairs = []
for fam in ("kitti2012", "kitti2015", "middlebury", "middeval3"):
    root = SD / fam
    for ref in discover(root, labeled=True):
        pairs.append((fam, ref))
eth = sorted((SD / "eth3d/two_view_training").iterdir())
for d in eth:
    pairs.append(("eth3d", d))
if only:
    pairs = [p for p in pairs if p[0] in only]
pairs = pairs[::step]

def load(fam, ref):
    if fam != "eth3d":
        p = ref.load()
        return p.key, to_gray(p.left), to_gray(p.right), p.disp, default_range(p)
    l, r = read_image(ref / "im0.png"), read_image(ref / "im1.png")
    gt = read_pfm(SD / "eth3d/two_view_training_gt" / ref.name / "disp0GT.pfm")
    gt = np.where(np.isfinite(gt), gt, np.nan).astype(np.float32)
    W = l.shape[1]
    c = dict(x.split("=", 1) for x in (ref / "calib.txt").read_text().split() if "=" in x)
    nd = min(int(c["ndisp"]), W - 1)  # ndisp = the width here: the largest range the method accepts
    return "eth3d/" + ref.name, to_gray(l), to_gray(r), gt, (0, nd)

matchers = {}
def matcher(key):
    if key not in matchers:
        if key == "auto":
            matchers[key] = StereoMatcher(max_disparity="auto", device=ctx, **kw)
        else:
            matchers[key] = StereoMatcher(max_disparity=key[1], min_disparity=key[0], device=ctx, **kw)
    return matchers[key]

rows = []
# warm-up: build every kernel once (census pipeline, coarse pass, range mask)
rng = np.random.default_rng(0)
wl = rng.random((60, 120)).astype(np.float32)
matcher("auto").compute(wl, np.roll(wl, -3, 1))
StereoMatcher(max_disparity=16, min_disparity=-4, device=ctx, **kw).compute(wl, np.roll(wl, -3, 1))
StereoMatcher(max_disparity=16, device=ctx, **kw).compute(wl, np.roll(wl, -3, 1))
for fam, ref in pairs:
    key, L, R, gt, (M, D) = load(fam, ref)
    thr = 3.0 if fam.startswith("kitti") else 2.0
    v = np.isfinite(gt)
    def err(d):
        return 100 * float(np.mean(np.abs(d[v] - gt[v]) > thr))
    ms = matcher((M, D)); ma = matcher("auto")
    # warm: first call per size builds buffers (and, once per process, kernels)
    def run_stated():
        c0, t0 = time.process_time(), time.perf_counter(); d = ms.compute(L, R)
        return d, time.perf_counter() - t0, time.process_time() - c0
    def run_auto():
        c0, t0 = time.process_time(), time.perf_counter(); info = ma.choose_range(L, R)
        d = ma.compute(L, R, disparity_range=info["range"])
        return d, info, time.perf_counter() - t0, time.process_time() - c0
    if len(rows) % 2:
        da, info, ta, ca = run_auto(); ds, ts, cs = run_stated()
    else:
        ds, ts, cs = run_stated(); da, info, ta, ca = run_auto()
    lo, hi = info["range"]
    out = float(np.mean((gt[v] < lo) | (gt[v] > hi)))
    row = dict(pair=key, family=fam, stated=[M, M + D - 1], auto=[lo, hi], err_stated=err(ds), err_auto=err(da),
               t_stated=ts, t_auto=ta, cpu_stated=cs, cpu_auto=ca, t_coarse=info["seconds"], outside=out, gt_min=float(np.nanmin(gt)),
               gt_max=float(np.nanmax(gt)), thr=thr)
    rows.append(row)
    print(json.dumps(row), flush=True)
    ms.release_buffers(); ma.release_buffers()
json.dump(rows, open(out_path, "w"), indent=1)
