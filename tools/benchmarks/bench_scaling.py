"""Scaling of the run time with image area and with the disparity range (issue #7).

Full-size measurement (run it on an idle machine; about 5 minutes on 2 idle
cores, of which ~4 min is the network):

    .venv/bin/python tools/benchmarks/bench_scaling.py --json scaling.json --plot docs/img/scaling.png

Quick check (tiny sizes, a few seconds; what tests/test_bench_scaling.py runs):

    .venv/bin/python tools/benchmarks/bench_scaling.py --quick --json /tmp/scaling.json

The pair is KITTI 2015 training 000000 (image_2 / image_3; data directory
``../shared/data`` or ``$MCCNN_DATA``), gray, cropped to its top rows
and left columns as each size needs (padded by repeating the last row up to
376 rows, as tools/benchmarks/bench_pipeline.py does).  Four series, three points each:

* stereo method, area: ``StereoMatcher(cost="census", max_disparity=228)`` on
  1240 x 94, 1240 x 188, 1240 x 376;
* stereo method, disparity range: 1240 x 376 at D = 57, 114, 228;
* network (``NetworkCost``, shipped weights), area: D = 32 (not 228) on
  1240 x 94, 1240 x 188, 1240 x 376;
* network, disparity range: 1240 x 94 (not 376) at D = 57, 114, 228.

The network is measured at a smaller D / height than the paper's 1240 x 376,
D = 228 (~250 s there per run) so the script finishes in minutes; the output
says so.  For the stereo method the times are those of
``compute(..., timings=True)`` grouped as CBCA (arms + both aggregation
passes, both references), SGM (both references), the rest (WTA, left-right
check, interpolation, subpixel, median, bilateral, uploads and the final
copy) and their sum, the total without the (census) cost.  Every point is the
best of ``--repeat`` runs after an untimed warm-up at the same size (for the
network with one disparity): programs are built per D, and PoCL compiles a
kernel again on its first launch with a new work-group size.

Each series is fitted by least squares with ``time = a + b * x`` (x = image
area in megapixels, or D) and with ``time = a + b * cells`` (cells = D x H' x
W' on the cost volume's domain, H' = H - 8, W' = W - 8; for the network only
the valid cells x >= d, the ones its head computes).  Reported per fit: a, b
(the per-unit cost), and the largest relative deviation of a point from the
line, ``max |t - (a + b x)| / t``.  With three points and two parameters that
deviation is the test of linearity: a few per cent on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from _paths import data_dir  # noqa: E402
DATA = data_dir()

MARGIN = 4  # half the 9x9 patch: the cost volume covers (H - 8) x (W - 8)

# Series: (name, method, what varies, fixed sizes/D, points as (width, height, D)).
FULL = {
    "stereo_area": ("stereo", "area", [(1240, 94, 228), (1240, 188, 228), (1240, 376, 228)]),
    "stereo_disp": ("stereo", "disparity", [(1240, 376, 57), (1240, 376, 114), (1240, 376, 228)]),
    "network_area": ("network", "area", [(1240, 94, 32), (1240, 188, 32), (1240, 376, 32)]),
    "network_disp": ("network", "disparity", [(1240, 94, 57), (1240, 94, 114), (1240, 94, 228)]),
}
QUICK = {
    "stereo_area": ("stereo", "area", [(96, 24, 16), (96, 48, 16), (96, 96, 16)]),
    "stereo_disp": ("stereo", "disparity", [(96, 48, 8), (96, 48, 16), (96, 48, 32)]),
    "network_area": ("network", "area", [(64, 20, 4), (64, 40, 4), (64, 80, 4)]),
    "network_disp": ("network", "disparity", [(64, 20, 4), (64, 20, 8), (64, 20, 16)]),
}

# StereoResult.timings keys -> group: mccnn_cl.benchmark.STAGE_GROUP (WTA ... bilateral are "rest").
STEREO_QUANTITIES = ("CBCA", "SGM", "rest", "total_excl_cost")
NETWORK_QUANTITIES = ("network",)


def kitti_gray(height=376, width=1240):
    """KITTI 2015 training 000000, gray uint8, top-left ``height`` x ``width``
    (last row / column repeated where the image is smaller)."""
    import cv2

    from mccnn_cl.io import read_image

    d = DATA / "kitti2015" / "training"
    paths = d / "image_2" / "000000_10.png", d / "image_3" / "000000_10.png"
    if not all(p.exists() for p in paths):
        sys.exit(f"KITTI 2015 000000 not found under {d} (set MCCNN_DATA)")
    out = []
    for p in paths:
        img = read_image(p, gray=True)[:height, :width]
        out.append(np.ascontiguousarray(cv2.copyMakeBorder(
            img, 0, height - img.shape[0], 0, width - img.shape[1], cv2.BORDER_REPLICATE)))
    return out


def cells(method, W, H, D):
    """Cost-volume cells the stage works on: all D x H' x W' for the stereo
    method, the valid ones (x >= d) for the network's head."""
    h, w = H - 2 * MARGIN, W - 2 * MARGIN
    if method == "stereo":
        return D * h * w
    return h * sum(max(w - d, 0) for d in range(D))


def fit(x, t):
    """Least-squares ``t = a + b x``: dict with a, b and the largest relative
    deviation of a point from the line."""
    x, t = np.asarray(x, float), np.asarray(t, float)
    A = np.stack([np.ones_like(x), x], axis=1)
    (a, b), *_ = np.linalg.lstsq(A, t, rcond=None)
    dev = np.abs(t - (a + b * x)) / t
    return {"a": float(a), "b": float(b), "max_rel_dev": float(dev.max()),
            "rel_dev": [float(v) for v in dev]}


def best_of(fn, repeat):
    """(seconds, payload) of the fastest of ``repeat`` calls of ``fn`` -> (seconds, payload)."""
    return min((fn() for _ in range(repeat)), key=lambda r: r[0])


def time_stereo(ctx, left, right, W, H, D, repeat):
    from mccnn_cl.pipeline import StereoMatcher

    m = StereoMatcher(cost="census", max_disparity=D, device=ctx)
    # warm-up at this very size: programs are built per D, and PoCL compiles
    # each kernel again for every new work-group size on its first launch
    m.compute(left[:H, :W], right[:H, :W])

    def run():
        t0 = time.perf_counter()
        res = m.compute(left[:H, :W], right[:H, :W], timings=True)
        return time.perf_counter() - t0, res.timings

    total, stages = best_of(run, repeat)
    from mccnn_cl.benchmark import group_timings

    g = group_timings(stages)
    out = {"CBCA": g["CBCA"], "SGM": g["SGM"], "total_excl_cost": total - g["cost"]}
    out["rest"] = out["total_excl_cost"] - g["CBCA"] - g["SGM"]
    out["cost"], out["total"] = g["cost"], total
    return out


def time_network(ctx, net, left, right, W, H, D, repeat):
    from mccnn_cl.pipeline import to_gray

    gl, gr = to_gray(left[:H, :W], "left"), to_gray(right[:H, :W], "right")
    net(gl, gr, 1).release()  # warm-up at this size (first launches), one disparity only
    ctx.finish()

    def run():
        t0 = time.perf_counter()
        d = net(gl, gr, D)
        ctx.finish()
        t = time.perf_counter() - t0
        d.release()
        return t, None

    return {"network": best_of(run, repeat)[0]}


def measure(args):
    from mccnn_cl.opencl.context import ClContext
    from mccnn_cl.costs.network import NetworkCost
    from mccnn_cl.weights import Weights, shipped_models

    spec = QUICK if args.quick else FULL
    ctx = ClContext(args.device)
    left, right = kitti_gray()
    load0 = os.getloadavg()[0]
    print(f"device: {ctx.describe()}; {os.cpu_count()} CPUs, load average {load0:.1f} at the start")
    print(f"pair: KITTI 2015 000000, gray, top-left crops; best of {args.repeat} after a warm-up"
          + ("; --quick: tiny sizes, a self-test only" if args.quick else ""))
    notes = []
    if not args.quick:
        notes.append("network measured at D = 32 for the area series and on 1240 x 94 for the disparity "
                     "series (the paper's 1240 x 376, D = 228 takes ~250 s per run)")
    for n in notes:
        print("note: " + n)
    net = None
    result = {"device": ctx.describe(), "cpu_count": os.cpu_count(), "repeat": args.repeat,
              "quick": bool(args.quick), "pair": "KITTI 2015 training 000000, gray, top-left crops",
              "notes": notes, "series": []}
    for name, (method, vary, points) in spec.items():
        if args.only and method not in args.only.split(","):
            continue
        if method == "network" and net is None:
            weights = Weights.load(shipped_models()["kitti-paper"])  # the paper network
            net = NetworkCost(ctx, weights)
        rows = []
        for W, H, D in points:
            if method == "stereo":
                times = time_stereo(ctx, left, right, W, H, D, args.repeat)
            else:
                times = time_network(ctx, net, left, right, W, H, D, args.repeat)
            rows.append({"width": W, "height": H, "D": D, "area_mpx": W * H / 1e6,
                         "cells": cells(method, W, H, D), "times": times})
            print(f"  {name:<13} {W:5d} x {H:3d}, D = {D:3d}: "
                  + ", ".join(f"{k} {v:.3f} s" for k, v in times.items()), flush=True)
        x_key = "area_mpx" if vary == "area" else "D"
        quantities = STEREO_QUANTITIES if method == "stereo" else NETWORK_QUANTITIES
        fits = {}
        for q in quantities:
            t = [r["times"][q] for r in rows]
            fits[q] = {"x": fit([r[x_key] for r in rows], t), "cells": fit([r["cells"] for r in rows], t)}
        result["series"].append({
            "name": name, "method": method, "vary": vary, "x_key": x_key,
            "x_unit": "Mpx" if vary == "area" else "disparity",
            "fixed": ({"D": points[0][2]} if vary == "area" else {"width": points[0][0], "height": points[0][1]}),
            "points": rows, "fits": fits})
    result["load_average"] = [load0, os.getloadavg()[0]]
    return result


def print_table(result):
    print(f"\nfits t = a + b x (largest deviation of a point from the line); "
          f"load average {result['load_average'][0]:.1f} -> {result['load_average'][1]:.1f}")
    print("| series | fixed | quantity | t at the 3 points (s) | a (s) | b per unit | max dev "
          "| b per cell (ns) | max dev (cells) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for s in result["series"]:
        fixed = ", ".join(f"{k} = {v}" for k, v in s["fixed"].items())
        xs = " / ".join(f"{r[s['x_key']]:g}" for r in s["points"])
        for q, f in s["fits"].items():
            ts = " / ".join(f"{r['times'][q]:.3f}" for r in s["points"])
            fx, fc = f["x"], f["cells"]
            unit = "s/Mpx" if s["vary"] == "area" else "s/disp"
            print(f"| {s['name']} (x = {xs}) | {fixed} | {q} | {ts} | {fx['a']:.3f} | {fx['b']:.4g} {unit} "
                  f"| {fx['max_rel_dev']:.1%} | {fc['b'] * 1e9:.3g} | {fc['max_rel_dev']:.1%} |")


def plot(result, path):
    """2 x 2 panels (stereo / network x area / D) with points and fitted lines.
    Returns False (and says so) when matplotlib is missing."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"matplotlib is not installed: plot {path} NOT written")
        return False
    panels = {("stereo", "area"): (0, 0), ("stereo", "disparity"): (0, 1),
              ("network", "area"): (1, 0), ("network", "disparity"): (1, 1)}
    fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
    for s in result["series"]:
        ax = axes[panels[(s["method"], s["vary"])]]
        x = np.array([r[s["x_key"]] for r in s["points"]])
        xl = np.linspace(0, x.max() * 1.05, 50)
        for q, f in s["fits"].items():
            t = [r["times"][q] for r in s["points"]]
            (line,) = ax.plot(xl, f["x"]["a"] + f["x"]["b"] * xl, "-", lw=1)
            ax.plot(x, t, "o", color=line.get_color(),
                    label=f"{q}: {f['x']['b']:.3g} s/{'Mpx' if s['vary'] == 'area' else 'disp'}, "
                          f"dev {f['x']['max_rel_dev']:.1%}")
        fixed = ", ".join(f"{k} = {v}" for k, v in s["fixed"].items())
        what = "stereo method (census cost)" if s["method"] == "stereo" else "network (shipped weights)"
        ax.set_title(f"{what}, {fixed}", fontsize=10)
        ax.set_xlabel("image area (Mpx)" if s["vary"] == "area" else "disparity range D")
        ax.set_ylabel("seconds")
        ax.set_xlim(0, None)
        ax.set_ylim(0, None)
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    for key, pos in panels.items():
        if not any((s["method"], s["vary"]) == key for s in result["series"]):
            axes[pos].set_visible(False)
    la = result["load_average"]
    fig.suptitle(f"{result['device'].split(' (')[0]}; {result['cpu_count']} CPUs; best of {result['repeat']}; load {la[0]:.1f}-{la[1]:.1f}"
                 + ("; QUICK (tiny sizes)" if result["quick"] else ""), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print(f"plot written to {path}")
    return True


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None, help="OpenCL device spec (see mccnn_cl.opencl.context.select_device)")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs per point after a warm-up; best is kept")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (seconds): a self-test, not a measurement")
    ap.add_argument("--only", default=None, help="comma-separated subset of stereo,network")
    ap.add_argument("--json", default=None, help="write the points and fits to this JSON file")
    ap.add_argument("--plot", default=None, help="write the 2 x 2 figure to this PNG (needs matplotlib)")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    if args.only and not set(args.only.split(",")) <= {"stereo", "network"}:
        ap.error("--only takes stereo, network or stereo,network")
    result = measure(args)
    print_table(result)
    if args.plot:
        result["plot"] = args.plot if plot(result, args.plot) else None
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)
        print(f"JSON written to {args.json}")


if __name__ == "__main__":
    main()
