"""The ``mccnn-cl`` command line (also ``python -m mccnn_cl``).

Sub-commands: ``match`` (one pair or a batch → disparity files, colour
pictures, depth, point clouds), ``evaluate`` (a dataset, beside OpenCV
SGBM), ``devices`` (OpenCL devices and the choice), ``bench`` (per-stage
timings), ``demo`` (the bundled MiddEval3 Adirondack pair) and ``adapt``
(self-training on unlabeled pairs, :mod:`mccnn_cl.cli.adapt`).  See docs/cli.md.
This module only parses and dispatches (:data:`COMMANDS`): ``match``,
``evaluate`` and ``devices`` and the helpers they share are implemented in
:mod:`mccnn_cl.cli.commands`, ``bench`` in :mod:`mccnn_cl.cli.bench`, ``demo`` in
:mod:`mccnn_cl.cli.demo`, ``convert-weights`` and ``models`` (parsers too) in
:mod:`mccnn_cl.cli.convert`; input checks are in :mod:`mccnn_cl.validate`.

Exit status: 0 success, 2 bad usage or input (:class:`~mccnn_cl.errors.InputError`
and argparse's errors), 1 runtime failure (OpenCL, anything unexpected), 130
interrupted, 141 stdout's reader went away (``mccnn-cl models | head -1``: the
command stops quietly, as a Unix tool killed by SIGPIPE, 128 + 13; :func:`_stdout_gone`;
the training modules' own entry points too, :func:`run_entry_point`).
Errors are one line on stderr; ``--verbose`` adds the traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
import traceback
import warnings

from .._version import __version__
from ..errors import InputError, MccnnError

DEMO_OUTPUT = "mccnn_demo.png"

#: sub-command -> (module, function) that implements it, imported when the
#: command runs; ``convert-weights`` and ``models`` set their own (``func``)
#: in :func:`mccnn_cl.cli.convert.add_parsers`.
COMMANDS = {
    "match": ("mccnn_cl.cli.commands", "cmd_match"),
    "evaluate": ("mccnn_cl.cli.commands", "cmd_evaluate"),
    "devices": ("mccnn_cl.cli.commands", "cmd_devices"),
    "bench": ("mccnn_cl.cli.bench", "run"),
    "demo": ("mccnn_cl.cli.demo", "run"),
    "adapt": ("mccnn_cl.cli.adapt", "run"),
    "tune": ("mccnn_cl.cli.tune", "run"),
}


# -- option groups -------------------------------------------------------------

def _matcher_options(p, default_disp_help):
    p.add_argument("--max-disp", type=int, default=None, metavar="N",
                   help=f"number of disparity levels D (disparities 0..D-1, or M..M+D-1 with --min-disp "
                        f"where offered); {default_disp_help}")
    p.add_argument("--cost", choices=("cnn", "census"), default="cnn",
                   help="matching cost: the MC-CNN network (default) or census (no network)")
    p.add_argument("--weights", metavar="FILE", default=None,
                   help="network weights: a .npz (mccnn_cl format), a published .t7/.pt network "
                        "(converted on the fly) or a shipped model's name (mccnn-cl models); "
                        "default: the shipped model")
    p.add_argument("--device", metavar="SPEC", default=None,
                   help="OpenCL device: gpu, cpu, PLATFORM[:DEVICE] name parts, or P:D indices "
                        "(default: $PYOPENCL_CTX, else GPU > accelerator > CPU)")
    p.add_argument("--memory-limit", type=float, default=None, metavar="MiB",
                   help="device memory the method may use, in MiB (default: 3/4 of the device's); larger "
                        "images run in row tiles (docs/method.md, 'Large images')")
    p.add_argument("--volume-dtype", choices=("float32", "float16"), default="float32",
                   help="storage of the cost volumes on the device: float16 halves their memory "
                        "(accuracy and speed: docs/method.md, 'Half-precision volumes')")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", dest="hyper",
                   help="stereo-method hyperparameter, e.g. --set sgm_pi2=64 --set interpolation=code "
                        "(names: mccnn_cl.pipeline.Hyperparameters); repeatable")


def _range_options(p):
    """--min-disp and --disp-range (match, evaluate): ranges not starting at 0, the automatic range."""
    p.add_argument("--min-disp", type=int, default=None, metavar="M",
                   help="smallest disparity searched, negative allowed: disparities M..M+D-1 with D = "
                        "--max-disp (default 0)")
    p.add_argument("--disp-range", default=None, metavar="auto|MIN:MAX",
                   help="'auto': coarse passes choose the range of each pair, in batches too (printed); "
                        "or MIN:MAX inclusive "
                        "(write --disp-range=-32:95 when MIN is negative); replaces --min-disp/--max-disp")


# -- parser and main ---------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    verbose = argparse.ArgumentParser(add_help=False)
    verbose.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                         help="log progress and show tracebacks on errors")
    p = argparse.ArgumentParser(
        prog="mccnn-cl",
        description="MC-CNN stereo matching (Zbontar & LeCun 2015) with OpenCL inference.",
        epilog="Exit status: 0 ok, 2 bad usage or input, 1 runtime failure, 130 interrupted, "
               "141 output pipe closed by its reader. See docs/cli.md.")
    p.add_argument("--version", action="version", version=f"mccnn-cl {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", default=False,
                   help="log progress and show tracebacks on errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    m = sub.add_parser("match", parents=[verbose], help="disparity map of one pair or a batch",
                       description="Match LEFT against RIGHT and write the left disparity map. "
                                   "Output format by extension: .pfm (Middlebury float, +inf invalid), "
                                   ".png (KITTI 16-bit, disparity*256, 0 invalid), .npy (float32, NaN invalid).")
    m.add_argument("left", nargs="?", help="left image")
    m.add_argument("right", nargs="?", help="right image")
    m.add_argument("-o", "--output", metavar="OUT", help="disparity file (.pfm, .png or .npy)")
    m.add_argument("-l", "--left-glob", metavar="GLOB", help="batch: left images (glob or folder)")
    m.add_argument("-r", "--right-glob", metavar="GLOB", help="batch: right images (glob or folder); a left and "
                   "a right image pair when the globs' wildcards match the same text: the same file name "
                   "(image_2/*.png, image_3/*.png) or folder (*/im0.png, */im1.png)")
    m.add_argument("--pairs-dir", metavar="DIR", help="batch: every folder at or under DIR with im0.* and im1.* "
                                                      "(Middlebury, ETH3D layouts) is a pair")
    m.add_argument("--output-dir", metavar="DIR", help="batch: folder for <pair name>.<format>")
    m.add_argument("--format", choices=("pfm", "png", "npy"), default="pfm", help="batch: output format")
    m.add_argument("--resume", action="store_true",
                   help="batch: skip pairs whose outputs are all written; redo the others whole")
    m.add_argument("--workers", type=int, default=None, metavar="N",
                   help="run on a Dask cluster of N local worker processes (one OpenCL device each, "
                        "GPUs shared out in turn); see docs/cli.md, 'Many pairs and huge images on Dask'")
    m.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="run on an existing Dask cluster (tcp://HOST:PORT or a scheduler file's address)")
    m.add_argument("--split-tiles", action="store_true",
                   help="with --workers/--scheduler: spread the row tiles of each tiled pair over the "
                        "workers (default: only when there are fewer pairs than workers)")
    _matcher_options(m, "default: ndisp from --calib if given, else 228 (KITTI)")
    _range_options(m)
    m.add_argument("--color", nargs="?", const="", default=None, metavar="FILE.png",
                   help="also write a colour picture with a disparity legend (default name: OUT without its extension + _color.png)")
    m.add_argument("--confidence", nargs="?", const="", default=None, metavar="FILE",
                   help="also write the per-pixel confidence in [0, 1], 0 where the left-right check failed: "
                        ".pfm/.npy float or .png 16-bit (confidence * 65535) (default name: <OUT>_confidence.pfm)")
    m.add_argument("--labels", nargs="?", const="", default=None, metavar="FILE",
                   help="also write the left-right labels (0 correct, 1 mismatch, 2 occlusion) as 8-bit .png "
                        "or .npy (default name: <OUT>_labels.png)")
    m.add_argument("--calib", metavar="FILE",
                   help="KITTI calib_cam_to_cam / calib or Middlebury calib.txt: also write depth "
                        "(<OUT>_depth.npy, or .pfm for .pfm output) and a coloured point cloud <OUT>.ply")
    m.add_argument("--ply-ascii", action="store_true", help="write the point cloud as ASCII PLY "
                                                            "(default binary little-endian)")
    m.add_argument("--force", action="store_true", help="overwrite existing output files")

    e = sub.add_parser("evaluate", parents=[verbose], help="errors on a dataset, beside OpenCV SGBM",
                       description="Match every pair with ground truth under DATASET_DIR (KITTI 2012/2015, "
                                   "Middlebury, MiddEval3 and ETH3D two-view layouts) and print, per dataset "
                                   "family, each pair's errors in that family's metrics (KITTI 3-px and D1; "
                                   "Middlebury and MiddEval3 bad-2.0; ETH3D bad-1.0 and bad-2.0; all and "
                                   "non-occluded GT) for MC-CNN beside OpenCV StereoSGBM and census, with the "
                                   "family means and whether the network was trained on each pair.")
    e.add_argument("dataset_dir", metavar="DATASET_DIR")
    e.add_argument("--dataset", choices=("kitti2012", "kitti2015", "middlebury", "eth3d"), default=None,
                   help="only pairs of this kind (default: every kind found)")
    e.add_argument("--pairs", metavar="NAME,...", help="only these pairs (names like Cones or 000000, "
                                                       "or keys like kitti2015/000000)")
    e.add_argument("--baseline", default="sgbm,census", metavar="LIST",
                   help="comparison methods, comma-separated: sgbm (OpenCV StereoSGBM), census (the census "
                        "cost through the same stereo method, its own settings), or none")
    _matcher_options(e, "default: the pair's ndisp (Middlebury calib.txt), else 228")
    _range_options(e)
    e.add_argument("--json", action="store_true", help="print the results as JSON")
    e.add_argument("--error-maps", metavar="DIR", help="write error-map PNGs here (green ok, red bad, "
                                                       "magenta no prediction, black no GT)")
    e.add_argument("--no-fill", action="store_true",
                   help="count pixels without a prediction as errors instead of filling them first")

    d = sub.add_parser("devices", parents=[verbose], help="list OpenCL devices and the one that would be used")
    d.add_argument("--device", metavar="SPEC", default=None, help="show which device SPEC selects")
    d.add_argument("--workers", type=int, default=None, metavar="N",
                   help="also show the device each of N local Dask workers would use (match --workers N)")

    t = sub.add_parser("tune", parents=[verbose], help="choose kernels by measurement on this device",
                       description="Measure the candidate kernel shapes of each tunable choice on the device, "
                                   "keep the fastest correct one in the per-device cache (~/.cache/mccnn_cl/tune), "
                                   "and store the kernel binaries of the default method (faster first calls). "
                                   "MCCNN_TUNE=off ignores the cache.")
    t.add_argument("--device", metavar="SPEC", default=None, help="OpenCL device (as for match)")
    t.add_argument("--no-binaries", action="store_true", help="do not store kernel binaries")
    t.add_argument("--size", metavar="HxWxD", default=None,
                   help="representative volume: rows x columns x disparity levels (default 96x1242x228: a quarter "
                        "of a KITTI pair's rows at its full width and range)")
    t.add_argument("--rounds", type=int, default=5, metavar="R",
                   help="interleaved rounds per candidate, best time kept (default 5)")

    b = sub.add_parser("bench", parents=[verbose], help="per-stage runtime on a KITTI-size pair",
                       description="Time each stage of the pipeline (best of --repeat runs after a "
                                   "warm-up) beside OpenCV SGBM on the same pair.")
    b.add_argument("--left", metavar="FILE", help="left image (default: a synthetic textured pair)")
    b.add_argument("--right", metavar="FILE", help="right image")
    b.add_argument("--size", default="1242x375", metavar="WxH", help="synthetic pair size (default KITTI)")
    b.add_argument("--repeat", type=int, default=1, help="timed runs (the best is shown)")
    b.add_argument("--no-warmup", action="store_true",
                   help="skip the untimed first run (then kernel builds count in the times)")
    _matcher_options(b, "default: 228")

    dm = sub.add_parser("demo", parents=[verbose], help="match the bundled MiddEval3 Adirondack pair",
                        description="Match the bundled demo pair (MiddEval3 Adirondack, 718x496, held out of "
                                    "training) with the shipped weights, compare with OpenCV SGBM and the "
                                    "ground truth, and write a colour picture.")
    dm.add_argument("-o", "--output", default=None, metavar="OUT.png",
                    help=f"picture to write (default {DEMO_OUTPUT}, which a later demo replaces)")
    dm.add_argument("--force", action="store_true", help="overwrite an OUT.png given with -o if it exists")
    _matcher_options(dm, "default: 73 (the demo's ndisp)")

    a = sub.add_parser("adapt", parents=[verbose], help="fine-tune a network to your camera without ground truth",
                       description="Self-training: pseudo-label your rectified pairs with the network (pixels the "
                                   "left-right check labels correct and whose confidence passes --min-confidence), "
                                   "fine-tune it on them, relabel, --rounds times; write the adapted weights. "
                                   "Needs PyTorch. See docs/training.md, 'Self-training and adapt'.")
    a.add_argument("left_glob", metavar="LEFT_GLOB", help="left images (glob or folder)")
    a.add_argument("right_glob", metavar="RIGHT_GLOB", help="right images (glob or folder), paired with the "
                                                            "left ones by sorted order")
    a.add_argument("--weights", required=True, metavar="FILE",
                   help="network to start from: a shipped name (kitti-fst), a .npz, or a published .t7/.pt")
    a.add_argument("-o", "--output", required=True, metavar="OUT.npz", help="adapted weights to write")
    a.add_argument("--ndisp", type=int, required=True, metavar="D",
                   help="disparity levels of your pairs (disparities 0..D-1), as for match --max-disp")
    a.add_argument("--rounds", type=int, default=2, help="label -> fine-tune rounds (default: %(default)s)")
    a.add_argument("--steps", type=int, default=250, help="crop-sampler SGD steps per round (default: %(default)s)")
    a.add_argument("--min-confidence", type=float, default=None, metavar="C",
                   help="confidence a pseudo-labeled pixel needs, in [0, 1] (default: the threshold chosen "
                        "on labeled training pairs, train.selftrain.DEFAULT_MIN_CONFIDENCE; docs/training.md)")
    a.add_argument("--lr", type=float, default=2e-4, help="fine-tuning learning rate, constant (default: %(default)s)")
    a.add_argument("--seed", type=int, default=0)
    a.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    a.add_argument("--device", metavar="SPEC", default=None, help="OpenCL device for the labelling (as for match)")
    a.add_argument("--run-dir", metavar="DIR", default=None,
                   help="keep each round's training files here (default: a temporary folder)")
    a.add_argument("--force", action="store_true", help="overwrite OUT.npz if it exists")

    from .convert import add_parsers  # convert-weights, models
    add_parsers(sub, [verbose])
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # --help, --version: argparse prints, ignoring a reader gone, and exits 0
    verbose = bool(getattr(args, "verbose", False))
    from ..opencl import context as cl

    compiler_output = cl.COMPILER_OUTPUT  # restored at the end: main may run in a process that goes on
    if verbose:
        logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
        cl.COMPILER_OUTPUT = True  # the compiler's "N warnings generated." lines and build logs
    _one_line_warnings()
    try:
        return _run(args, verbose)
    finally:
        cl.COMPILER_OUTPUT = compiler_output


def _run(args, verbose) -> int:
    """The command's exit status, its errors reported in one line (a traceback with ``verbose``)."""
    try:
        code = int(_implementation(args)(args) or 0)
        sys.stdout.flush()  # what is still buffered: a reader gone by now is a broken pipe too
        return code
    except BrokenPipeError:
        return _stdout_gone()
    except KeyboardInterrupt:
        print("mccnn-cl: interrupted", file=sys.stderr)
        return 130
    except InputError as exc:
        return _fail(exc, 2, verbose)
    except MccnnError as exc:
        return _fail(exc, 1, verbose)
    except Exception as exc:  # noqa: BLE001 - the command line reports everything in one line
        return _fail(exc, 1, verbose, with_type=True)


#: exit status when stdout's reader went away: the shell's for a process killed by SIGPIPE (128 + 13)
BROKEN_PIPE_STATUS = 141


def _stdout_gone() -> int:
    """stdout is a pipe whose reader stopped (``mccnn-cl models | head -1``): end quietly, as a
    Unix tool does.  stdout is pointed at /dev/null so that the interpreter's last flush of what is
    still buffered does not fail a second time ("Exception ignored ... BrokenPipeError"); the status
    is :data:`BROKEN_PIPE_STATUS`, what a shell reports for a tool killed by SIGPIPE."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (AttributeError, OSError, ValueError):  # no real file behind sys.stdout (captured in-process)
        pass
    return BROKEN_PIPE_STATUS


def run_entry_point(main, argv=None):
    """``main(argv)``'s exit status, for a command with an entry point of its own (``python -m
    mccnn_cl.train.train`` and the other training modules' ``__main__``): a reader of stdout gone
    (``| head -1``) ends it as it ends ``mccnn-cl`` (:func:`_stdout_gone`, exit status
    :data:`BROKEN_PIPE_STATUS`, no traceback).  What is still buffered is flushed here, so that a
    reader gone by the end counts too.  The command's other errors are its own to report."""
    try:
        code = main(argv)
        sys.stdout.flush()
        return code
    except BrokenPipeError:
        return _stdout_gone()


def _one_line_warnings():
    """InputWarnings (a swapped pair, 12-bit data, ...) as one line on stderr,
    ``mccnn-cl: warning: ...``, each once; other warnings as Python shows them."""
    from ..errors import InputWarning

    shown = warnings.showwarning
    if getattr(shown, "mccnn_one_line", False):
        return

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, InputWarning):
            print(f"mccnn-cl: warning: {message}", file=sys.stderr)
        else:
            shown(message, category, filename, lineno, file, line)
    show.mccnn_one_line = True
    warnings.showwarning = show


def _implementation(args):
    """The function that runs ``args.command`` (:data:`COMMANDS`, else the parser's ``func``)."""
    if args.command in COMMANDS:
        module, name = COMMANDS[args.command]
        return getattr(importlib.import_module(module), name)
    return args.func


def _fail(exc, code, verbose, with_type=False) -> int:
    if verbose:
        traceback.print_exc()
    text = str(exc).strip() or type(exc).__name__
    lines = text.splitlines()
    msg = lines[0] if lines else text
    if with_type:
        msg = f"{type(exc).__name__}: {msg}"
    if len(lines) > 1 and not verbose:
        msg += " (--verbose for details)"
    print(f"mccnn-cl: error: {msg}", file=sys.stderr)
    return code
