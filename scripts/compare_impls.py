"""Agreement of the whole stereo method between OpenCL implementations.

    .venv/bin/python scripts/compare_impls.py [--impls pocl intel] [--cost census cnn]
                                              [--pairs tsukuba venus cones kitti2015] [--weights PATH]

Runs :class:`mccnn_cl.pipeline.StereoMatcher` on real pairs from
``../shared/data`` (or ``$MCCNN_DATA``) once per implementation, each
in its own process whose ICD loader sees only that implementation
(``scripts/opencl_impls.sh --env``), then compares every implementation with
the first: the matching cost volume (max |diff|), the integer disparity
D_INT (% equal) and the final disparity (% of pixels within 0.5 px and
within 0.01 px, max |diff|).  ``--cost cnn`` uses ``--weights`` (a file, or
``random`` for a mid-sized random net) or the shipped model (skipped with a
note when neither exists).  Prints a Markdown table
(the figures in docs/portability.md come from it).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

# name -> (relative dir or (dir, left, right), max_disparity, crop (y0, y1, x0, x1) or None)
PAIRS = {
    "tsukuba": ("middlebury/Tsukuba", "im0.png", "im1.png", 16, None),
    "venus": ("middlebury/Venus", "im0.png", "im1.png", 32, None),
    "cones": ("middlebury/Cones", "im0.png", "im1.png", 64, None),
    # KITTI 2015 000000: a 375 x 620 crop with D = 128 (the full 228 x 1242
    # volume is ~0.4 GB per copy; the crop keeps the run short on 2 cores)
    "kitti2015": ("kitti2015/training", "image_2/000000_10.png", "image_3/000000_10.png", 128,
                  (0, 375, 300, 920)),
}


def _data_dir() -> Path:
    return Path(os.environ.get("MCCNN_DATA", REPO.parent / "shared" / "data"))


def _load(name):
    import cv2

    rel, l, r, D, crop = PAIRS[name]
    d = _data_dir() / rel
    left = cv2.imread(str(d / l), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(d / r), cv2.IMREAD_GRAYSCALE)
    if left is None or right is None:
        raise SystemExit(f"cannot read {name} from {d}")
    if crop:
        y0, y1, x0, x1 = crop
        left, right = left[y0:y1, x0:x1], right[y0:y1, x0:x1]
    return left, right, D


def worker(args) -> int:
    """Inside one implementation's process: run the pairs, save arrays to --out."""
    from mccnn_cl.opencl.context import ClContext
    from mccnn_cl.pipeline import StereoMatcher

    ctx = ClContext()
    out = Path(args.out)
    info = {"device": ctx.describe(), "runs": {}}
    for cost in args.cost:
        weights = None
        if cost == "cnn":
            from mccnn_cl.weights import Weights

            try:
                if args.weights == "random":  # a mid-sized random net: agreement only, no accuracy
                    weights = Weights.random(conv_layers=[[32, 3]] * 4, fc_layers=[128, 128, 128, 2], seed=0)
                else:
                    weights = Weights.load(args.weights) if args.weights else Weights.load()
            except Exception as exc:  # noqa: BLE001 - reported, not fatal
                info["runs"][cost] = f"skipped: no weights ({exc})"
                continue
        for name in args.pairs:
            left, right, D = _load(name)
            m = StereoMatcher(weights=weights, max_disparity=D, device=ctx, cost=cost)
            t0 = time.perf_counter()
            res = m.compute(left, right, return_intermediates=True)
            secs = time.perf_counter() - t0
            key = f"{cost}-{name}"
            np.save(out / f"{key}-disp.npy", res.disparity)
            np.save(out / f"{key}-cost.npy", res.intermediates["C_CNN"])
            np.save(out / f"{key}-dint.npy", res.intermediates["D_INT"])
            info["runs"][key] = round(secs, 1)
            print(f"{ctx.describe()}: {key} {left.shape[1]}x{left.shape[0]} D={D}: {secs:.1f} s",
                  file=sys.stderr, flush=True)
    (out / "info.json").write_text(json.dumps(info))
    return 0


def _impl_env(impl: str) -> dict:
    proc = subprocess.run(["bash", str(REPO / "scripts" / "opencl_impls.sh"), "--no-install", "--env", impl],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(proc.stderr.strip())
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("OCLGRIND_", "PYOPENCL_CTX", "RUSTICL_", "OCL_ICD_"))}
    env.update(dict(line.split("=", 1) for line in proc.stdout.splitlines() if "=" in line))
    if impl == "oclgrind":
        env["OCLGRIND_LOG"] = os.devnull
    return env


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--impls", nargs="+", default=["pocl", "intel"])
    ap.add_argument("--cost", nargs="+", default=["census", "cnn"], choices=["census", "cnn"])
    ap.add_argument("--pairs", nargs="+", default=list(PAIRS), choices=list(PAIRS))
    ap.add_argument("--weights", help="weights file for --cost cnn (default: the shipped model; "
                    "'random': a mid-sized random net, 4 x 32 maps, 3 x 128 hidden)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker(args)

    with tempfile.TemporaryDirectory(prefix="mccnn-compare-") as tmp:
        infos = {}
        for impl in args.impls:
            d = Path(tmp) / impl
            d.mkdir()
            cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--out", str(d),
                   "--cost", *args.cost, "--pairs", *args.pairs]
            if args.weights:
                cmd += ["--weights", args.weights]
            subprocess.run(cmd, env=_impl_env(impl), check=True)
            infos[impl] = json.loads((d / "info.json").read_text())
        base = args.impls[0]
        print(f"\nReference: {base} = {infos[base]['device']}")
        for impl in args.impls[1:]:
            print(f"Compared:  {impl} = {infos[impl]['device']}")
        print("\n| cost | pair | impl | C max abs diff | D_INT equal | disp within 0.5 px | within 0.01 px "
              "| max abs diff | time base / impl (s) |")
        print("|---|---|---|---|---|---|---|---|---|")
        for key, secs in infos[base]["runs"].items():
            if isinstance(secs, str):
                print(f"| {key} | {secs} |")
                continue
            cost, pair = key.split("-", 1)
            a_disp = np.load(Path(tmp) / base / f"{key}-disp.npy")
            a_cost = np.load(Path(tmp) / base / f"{key}-cost.npy")
            a_dint = np.load(Path(tmp) / base / f"{key}-dint.npy")
            for impl in args.impls[1:]:
                b_disp = np.load(Path(tmp) / impl / f"{key}-disp.npy")
                b_cost = np.load(Path(tmp) / impl / f"{key}-cost.npy")
                b_dint = np.load(Path(tmp) / impl / f"{key}-dint.npy")
                valid = ~np.isnan(a_cost)
                assert np.array_equal(valid, ~np.isnan(b_cost)), f"{key}: NaN patterns differ"
                cdiff = float(np.max(np.abs(a_cost[valid] - b_cost[valid])))
                ddiff = np.abs(a_disp.astype(np.float64) - b_disp)
                print(f"| {cost} | {pair} {a_disp.shape[1]}x{a_disp.shape[0]} | {impl} | {cdiff:.2e} "
                      f"| {100 * np.mean(a_dint == b_dint):.2f} % | {100 * np.mean(ddiff <= 0.5):.2f} % "
                      f"| {100 * np.mean(ddiff <= 0.01):.2f} % | {ddiff.max():.3f} "
                      f"| {secs} / {infos[impl]['runs'][key]} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
