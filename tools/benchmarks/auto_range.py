"""The automatic disparity range against the stated one on the shared pairs
(docs/method.md, "Disparity ranges"): per pair the error of both, their wall
and CPU seconds (time.process_time: PoCL's threads included), the coarse
passes' seconds and the fraction of ground-truth pixels outside the chosen
range; one JSON line per pair, appended to OUT.jsonl as it is measured (a
rerun skips the pairs OUT.jsonl already holds) and printed.

    MEM_GIB=2 python tools/benchmarks/auto_range.py census|WEIGHTS OUT.jsonl [family,...]
    python tools/benchmarks/auto_range.py table OUT.jsonl    # the per-family table (markdown)

Families: kitti2012, kitti2015, middlebury, middeval3, eth3d (every labeled
pair :func:`mccnn_cl.evaluation.datasets.discover` finds; the stated range is
:func:`mccnn_cl.evaluation.scoring.default_range`: KITTI 228 levels, calib.txt
ndisp (widened to MiddEval3's vmin/vmax), ETH3D :data:`ETH3D_NDISP`).  EVERY=N
takes every Nth pair.  Errors on every ground-truth pixel: 3-px for KITTI,
bad-2.0 otherwise.  Data: $MCCNN_DATA, default ../shared/data."""
import json, os, sys, time
from pathlib import Path
import numpy as np

from _paths import data_dir  # noqa: E402
from mccnn_cl import StereoMatcher
from mccnn_cl.opencl.context import ClContext
from mccnn_cl.evaluation.datasets import discover, to_gray_u8 as to_gray
from mccnn_cl.evaluation.scoring import default_range

NAMES = {"kitti2012": "KITTI 2012", "kitti2015": "KITTI 2015", "middlebury": "Middlebury 2001–2006",
         "middeval3": "MiddEval3 (quarter)", "eth3d": "ETH3D two-view"}


def table(rows):
    """Markdown: one line per family, then the whole set."""
    def rng(a, b):
        return f"{a}–{b}" if a != b else f"{a}"
    out = ["| family (pairs) | stated range | auto range (levels) | error, stated | error, auto "
           "| Δ per pair (min … max) | CPU s stated | CPU s auto (coarse passes) | GT outside the auto range |",
           "|---|---|---|---|---|---|---|---|---|"]
    for fam in NAMES:
        rs = [r for r in rows if r["family"] == fam]
        if not rs:
            continue
        n = len(rs)
        his = sorted({r["stated"][1] for r in rs})
        stated = f"0 … {rng(his[0], his[-1])}"
        lv = [r["auto"][1] - r["auto"][0] + 1 for r in rs]
        deltas = sorted((r["err_auto"] - r["err_stated"], r["pair"].split("/")[-1]) for r in rs)
        metric = "3-px" if fam.startswith("kitti") else "bad-2"
        outside = [r["outside"] for r in rs]
        out.append(f"| {NAMES[fam]} ({n}) | {stated} | {min(r['auto'][0] for r in rs)} … "
                   f"{max(r['auto'][1] for r in rs)} ({min(lv)}–{max(lv)}) "
                   f"| {sum(r['err_stated'] for r in rs) / n:.2f} % ({metric}) "
                   f"| {sum(r['err_auto'] for r in rs) / n:.2f} % "
                   f"| {deltas[0][0]:+.2f} ({deltas[0][1]}) … {deltas[-1][0]:+.2f} ({deltas[-1][1]}) "
                   f"| {sum(r['cpu_stated'] for r in rs):.1f} | {sum(r['cpu_auto'] for r in rs):.1f} "
                   f"({sum(r['cpu_coarse'] for r in rs):.1f}) "
                   f"| {sum(outside) / n:.3f} % mean, {max(outside):.2f} % max; "
                   f"{sum(o > 0 for o in outside)} of {n} pairs |")
    cs, ca = sum(r["cpu_stated"] for r in rows), sum(r["cpu_auto"] for r in rows)
    ws, wa = sum(r["t_stated"] for r in rows), sum(r["t_auto"] for r in rows)
    loads = [r["load"] for r in rows]
    out.append(f"\n{len(rows)} pairs (load average {min(loads):.1f}–{max(loads):.1f}): CPU s {cs:.1f} stated, "
               f"{ca:.1f} auto ({100 * ca / cs:.0f} %), coarse passes "
               f"{sum(r['cpu_coarse'] for r in rows):.1f}; wall s {ws:.1f} / {wa:.1f}; pairs within 0.3 points: "
               f"{sum(abs(r['err_auto'] - r['err_stated']) <= 0.3 for r in rows)}, worse by more: "
               f"{sum(r['err_auto'] - r['err_stated'] > 0.3 for r in rows)}")
    for r in rows:
        d = r["err_auto"] - r["err_stated"]
        if abs(d) > 0.3 or r["outside"] > 0.1:
            out.append(f"exception {r['pair']}: {r['stated']} -> {r['auto']}, {r['err_stated']:.2f} -> "
                       f"{r['err_auto']:.2f} ({d:+.2f}), GT {r['gt_min']:.1f} … {r['gt_max']:.1f}, outside "
                       f"{r['outside']:.3f} % (below {r['below']:.3f}, above {r['above']:.3f})")
    return "\n".join(out)


if len(sys.argv) > 2 and sys.argv[1] == "table":
    print(table([json.loads(line) for line in Path(sys.argv[2]).read_text().splitlines() if line.strip()]))
    sys.exit(0)

SD = data_dir()
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
