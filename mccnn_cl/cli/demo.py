"""``mccnn-cl demo``: the bundled MiddEval3 Adirondack pair (``mccnn_cl/demo/``, a
data folder; hence this module's name; :func:`load_demo_pair`) matched with the
shipped network, beside OpenCV SGBM and the ground truth, and one picture of
the four (:func:`compose_picture`).  The parser lives in :mod:`mccnn_cl.cli`,
the shared helpers in :mod:`mccnn_cl.cli.commands`.
"""

from __future__ import annotations

import os
import time
from contextlib import ExitStack
from importlib import resources

import numpy as np

from ..errors import InputError
from .common import counted

#: The bundled pair's key as the datasets' loaders name it (MiddEval3 training, quarter size).
DEMO_KEY = "middlebury/trainingQ/Adirondack"


def demo_dir():
    """Context manager yielding the folder of the bundled demo pair."""
    return resources.as_file(resources.files("mccnn_cl") / "demo")


def load_demo_pair(folder):
    """The demo pair as a :class:`~mccnn_cl.evaluation.datasets.StereoPair`: a MiddEval3
    scene folder whose ground truth is ``disp0GT.png``, a KITTI-format 16-bit PNG
    (disparity × 256, 0 = unknown), in place of the 1.4 MB float PFM."""
    from pathlib import Path

    from ..evaluation.datasets import load_middlebury
    from ..io import read_image, read_kitti_disparity

    folder = Path(folder)
    pair = load_middlebury(folder)
    disp, valid = read_kitti_disparity(folder / "disp0GT.png")
    mask = read_image(folder / "mask0nocc.png", gray=True)
    if disp.shape != pair.shape or mask.shape != pair.shape:
        raise InputError(f"{folder}: disp0GT.png {disp.shape} / mask0nocc.png {mask.shape} "
                         f"do not match im0.png {pair.shape}")
    pair.disp = np.where(valid, disp, np.float32(np.nan)).astype(np.float32)
    pair.valid_all, pair.valid_noc = valid, valid & (mask == 255)
    pair.kind, pair.name = DEMO_KEY.split("/", 1)
    return pair


def compose_picture(left_bgr, gt, ours, base, vmax, captions) -> np.ndarray:
    """Left image | GT on top, ours | SGBM below, each with its caption, and one
    disparity legend under them (uint8 BGR).  Images narrower than 360 px are
    shown at 2x (nearest: crisp pixels, room for the caption)."""
    import cv2

    from ..visualize import colorize, label, legend_bar

    zoom = 2 if left_bgr.shape[1] < 360 else 1

    def tile(img, caption):
        big = cv2.resize(img, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST) if zoom > 1 else img
        return label(big, caption, height=24, scale=0.5)

    tiles = [tile(left_bgr, captions[0])] + [tile(colorize(d, 0, vmax), c) for d, c in zip((gt, ours, base), captions[1:])]
    gap = np.full((tiles[0].shape[0], 6, 3), 255, np.uint8)
    top = np.hstack([tiles[0], gap, tiles[1]])
    bottom = np.hstack([tiles[2], gap, tiles[3]])
    sep = np.full((6, top.shape[1], 3), 255, np.uint8)
    return np.vstack([top, sep, bottom, sep, legend_bar(top.shape[1], 0, vmax, height=40, scale=0.5)])


def run(args) -> int:
    """The ``demo`` sub-command: match, print the error table, write the picture."""
    import cv2

    from . import commands
    from ..evaluation.baseline import sgbm
    from ..evaluation.scoring import training_status
    from ..io import write_image
    from ..evaluation.metrics import evaluate_disparity, fill_invalid
    from ..validate import check_pair, patch_size
    from ..weights import default_weights_path
    say = commands._say
    from . import DEMO_OUTPUT
    out = args.output or DEMO_OUTPUT  # the default picture is the demo's own: a second run replaces it
    if not out.lower().endswith((".png", ".jpg", ".jpeg", ".bmp")):
        raise InputError(f"{out}: the demo writes a picture; use a .png or .jpg name")
    commands._check_outputs([out], args.force or args.output is None)
    with ExitStack() as stack:
        pair = load_demo_pair(stack.enter_context(demo_dir()))
    max_disp = pair.ndisp if args.max_disp is None else commands._positive("--max-disp", args.max_disp)
    weights = commands._load_weights(args)
    left, right = pair.gray()
    check_pair(left, right, max_disp, patch_size(weights))
    status = training_status(weights.meta, pair.key, "Adirondack") if weights is not None else "n/a"
    t0 = time.perf_counter()
    matcher = commands._make_matcher(args, max_disp, weights, progress=commands._tty())
    t_setup = time.perf_counter() - t0
    ctx = matcher.ctx
    built = ctx.build_seconds
    t0 = time.perf_counter()
    ours = matcher.compute(left, right)
    # kernels built lazily inside the first call are one-time set-up, not matching
    lazy = ctx.build_seconds - built
    t_ours = time.perf_counter() - t0 - lazy
    t_setup += lazy
    base, t_base = sgbm(left, right, max_disp, return_time=True)
    m_ours = evaluate_disparity(fill_invalid(ours), pair.disp, pair.valid_noc, pair.valid_all)
    m_base = evaluate_disparity(fill_invalid(base), pair.disp, pair.valid_noc, pair.valid_all)
    n_gt, n_noc = int(pair.valid_all.sum()), int(pair.valid_noc.sum())
    h, w = left.shape
    say(f"demo pair: MiddEval3 Adirondack, quarter size ({w}x{h}), {max_disp} disparities, "
        "ground truth from structured light")
    if weights is None:
        say("cost:      census (no network)")
    else:
        name = (os.path.basename(args.weights) if args.weights else
                os.path.basename(default_weights_path()) + " (shipped)")
        phrase = {"held out": "Adirondack was held out of their training",
                  "trained": "Adirondack was one of their TRAINING pairs",
                  "unknown": "they do not record their training pairs"}[status]
        say(f"weights:   {name}; {phrase}")
    say(f"{'method':<22} {'bad-2.0':>9} {'bad-2 noc':>9} {'3-px err':>9} {'EPE':>8} {'time':>8}")
    label_ours = "MC-CNN (OpenCL)" if args.cost == "cnn" else "census+SGM (OpenCL)"
    for name, m, t in ((label_ours, m_ours, t_ours), ("OpenCV SGBM", m_base, t_base)):
        say(f"{name:<22} {m['bad2_all']:>8.2f}% {m['bad2_noc']:>8.2f}% {m['bad3_all']:>8.2f}% "
            f"{m['epe_all']:>6.2f}px {t:>7.3f}s")
    say(f"(errors in % of the {n_gt} pixels with ground truth, 'noc' of the {n_noc} non-occluded ones; "
        f"SGBM's holes filled as the KITTI devkit "
        f"does; one-time OpenCL set-up, not in the time: {t_setup:.1f} s on {ctx.device.name.strip()}, "
        f"{counted(ctx.builds, 'kernel build')}, {counted(ctx.binary_loads, 'stored binary', 'stored binaries')})")
    left_bgr = cv2.cvtColor(left, cv2.COLOR_GRAY2BGR) if pair.left.ndim == 2 else pair.left
    captions = ("left image", "ground truth (black: unknown)",
                f"{label_ours}: bad-2.0 {m_ours['bad2_all']:.1f} %, 3-px {m_ours['bad3_all']:.1f} %",
                f"OpenCV SGBM: bad-2.0 {m_base['bad2_all']:.1f} %, 3-px {m_base['bad3_all']:.1f} %")
    write_image(out, compose_picture(left_bgr, pair.disp, ours, base, max_disp - 1, captions))
    say(f"wrote {out}")
    return 0
