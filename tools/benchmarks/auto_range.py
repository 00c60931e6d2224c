"""The automatic disparity range against the stated one on the shared pairs
(docs/method.md, "Disparity ranges"): per pair the error of both, their wall
and CPU seconds (time.process_time: PoCL's threads included), the coarse
passes' seconds and the fraction of ground-truth pixels outside the chosen
range; one JSON line per pair, appended to OUT.jsonl as it is measured (a
rerun skips the pairs OUT.jsonl already holds) and printed.

    MEM_GIB=2 python tools/benchmarks/auto_range.py census|WEIGHTS OUT.jsonl [family,...]

Families: kitti2012, kitti2015, middlebury, middeval3, eth3d (every labeled
pair :func:`mccnn_cl.evaluation.datasets.discover` finds; the stated range is
:func:`mccnn_cl.evaluation.scoring.default_range`: KITTI 228 levels, calib.txt
ndisp (widened to MiddEval3's vmin/vmax), ETH3D :data:`ETH3D_NDISP`).  EVERY=N
takes every Nth pair.  Errors on every ground-truth pixel: 3-px for KITTI,
bad-2.0 otherwise.  Data: MCCNN_SHARED_DATA, default ../shared/data."""
import json, os, sys, time
from pathlib import Path
import numpy as np
from mccnn_cl import StereoMatcher
from mccnn_cl.opencl.context import ClContext
from mccnn_cl.evaluation.datasets import discover, to_gray_u8 as to_gray
from mccnn_cl.evaluation.scoring import default_range

SD = Path(os.environ.get("MCCNN_SHARED_DATA", Path(__file__).resolve().parents[2] / ".." / "shared" / "data"))
FAMILIES = ("kitti2012", "kitti2015", "middlebury", "middeval3", "eth3d")
cost = sys.argv[1]
out_path = Path(sys.argv[2])
only = sys.argv[3].split(",") if len(sys.argv) > 3 else FAMILIES
ctx = ClContext(None)
kw = dict(cost="census") if cost == "census" else dict(weights=cost)
kw["memory_limit"] = int(float(os.environ.get("MEM_GIB", "2")) * 2**30)  # the same for both runs
step = int(os.environ.get("EVERY", "1"))
pairs = [(fam, ref) for fam in FAMILIES if fam in only for ref in discover(SD / fam, labeled=True)][::step]
done = set()
if out_path.exists():
    done = {json.loads(line)["pair"] for line in out_path.read_text().splitlines() if line.strip()}

matchers = {}
def matcher(key):
    if key not in matchers:
        if key == "auto":
            matchers[key] = StereoMatcher(max_disparity="auto", device=ctx, **kw)
        else:
            matchers[key] = StereoMatcher(max_disparity=key[1], min_disparity=key[0], device=ctx, **kw)
    return matchers[key]

# warm-up: build every kernel once (census pipeline, coarse passes, range mask)
rng = np.random.default_rng(0)
wl = rng.random((60, 120)).astype(np.float32)
matcher("auto").compute(wl, np.roll(wl, -3, 1))
StereoMatcher(max_disparity=16, min_disparity=-4, device=ctx, **kw).compute(wl, np.roll(wl, -3, 1))
StereoMatcher(max_disparity=16, device=ctx, **kw).compute(wl, np.roll(wl, -3, 1))
n = 0
for fam, ref in pairs:
    p = ref.load()
    if p.key in done:
        continue
    L, R, gt, (M, D) = to_gray(p.left), to_gray(p.right), p.disp, default_range(p)
    thr = 3.0 if fam.startswith("kitti") else 2.0
    v = np.isfinite(gt)
    def err(d):
        return 100 * float(np.mean(np.abs(d[v] - gt[v]) > thr))
    ms = matcher((M, D)); ma = matcher("auto")
    def run_stated():
        c0, t0 = time.process_time(), time.perf_counter(); d = ms.compute(L, R)
        return d, time.perf_counter() - t0, time.process_time() - c0
    def run_auto():
        c0, t0 = time.process_time(), time.perf_counter(); info = ma.choose_range(L, R)
        c1 = time.process_time()
        d = ma.compute(L, R, disparity_range=info["range"])
        return d, info, time.perf_counter() - t0, time.process_time() - c0, c1 - c0
    if n % 2:  # alternate which side runs first
        da, info, ta, ca, cc = run_auto(); ds, ts, cs = run_stated()
    else:
        ds, ts, cs = run_stated(); da, info, ta, ca, cc = run_auto()
    n += 1
    lo, hi = info["range"]
    g = gt[v]
    row = dict(pair=p.key, family=fam, stated=[M, M + D - 1], auto=[lo, hi], err_stated=err(ds), err_auto=err(da),
               t_stated=ts, t_auto=ta, cpu_stated=cs, cpu_auto=ca, cpu_coarse=cc, t_coarse=info["seconds"],
               found=list(info["found"]), check=info["check"],
               outside=100 * float(np.mean((g < lo) | (g > hi))), below=100 * float(np.mean(g < lo)),
               above=100 * float(np.mean(g > hi)), gt_min=float(g.min()), gt_max=float(g.max()), thr=thr,
               load=os.getloadavg()[0])
    print(json.dumps(row), flush=True)
    with open(out_path, "a") as f:
        f.write(json.dumps(row) + "\n")
    ms.release_buffers(); ma.release_buffers()
