"""Bodies of ``mccnn-cl match``, ``evaluate`` and ``devices`` and the helpers
every sub-command shares (the parser and the dispatch live in :mod:`mccnn_cl.cli`).

:func:`cmd_match` writes one pair or a batch (disparity by extension, colour
picture, depth and point cloud with ``--calib``, confidence and labels);
:func:`cmd_evaluate` scores a dataset beside OpenCV SGBM; :func:`cmd_devices`
lists OpenCL devices and the choice.  The shared helpers -- :func:`_load_weights`
(weights checked before any OpenCL work), :func:`_make_matcher` (options and
``--set`` hyperparameters to a StereoMatcher), :func:`_check_outputs`,
:func:`_gray`, :func:`_tty`, :func:`_say` -- are also used by
:mod:`mccnn_cl.cli.bench` and :mod:`mccnn_cl.cli.demo`.  Bad input raises
:class:`~mccnn_cl.errors.InputError`; :func:`mccnn_cl.cli.main` turns it into
one line and exit status 2.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
import sys
import time

import numpy as np

from ..errors import InputError, WeightsError

DISPARITY_FORMATS = (".pfm", ".png", ".npy")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp", ".tif", ".tiff", ".webp")


# -- helpers ---------------------------------------------------------------

def _say(*args):
    print(*args, flush=True)


def _positive(name, value):
    if value is not None and value < 1:
        raise InputError(f"{name} must be >= 1, got {value}")
    return value


def _load_weights(args):
    """The Weights the matcher will use (checked now, so a bad file fails before any OpenCL work)."""
    if args.cost != "cnn":
        if getattr(args, "weights", None) is not None:
            raise InputError(f"--weights is for --cost cnn; --cost {args.cost} uses no network "
                             f"(drop --weights {args.weights} or the --cost option)")
        _check_settings(args, None)
        return None
    from ..models import resolve
    from ..weights import default_weights_path
    if args.weights is None and not os.path.exists(default_weights_path()):
        raise WeightsError(f"the shipped weights are not installed ({default_weights_path()}); "
                           "pass --weights FILE or use --cost census")
    weights = resolve(args.weights)  # .npz, .t7/.pt (converted), or a shipped model's name
    _check_settings(args, weights)
    return weights


def _check_settings(args, weights):
    """--set values, the weights' settings and --memory-limit, before any OpenCL work
    (:func:`mccnn_cl.validate.check_settings`: the checks StereoMatcher makes)."""
    from ..validate import check_settings
    _memory_limit(args)
    try:
        check_settings(weights, _hyperparameters(getattr(args, "hyper", []) or []),
                       getattr(args, "weights", None) or "the shipped weights")
    except TypeError as exc:  # unknown hyperparameter name
        raise InputError(f"--set: {exc}") from exc


def _memory_limit(args):
    """--memory-limit in bytes (None: the default); a positive finite number of MiB."""
    limit = getattr(args, "memory_limit", None)
    if limit is None:
        return None
    if not (math.isfinite(limit) and limit > 0):
        raise InputError(f"--memory-limit must be a positive number of MiB, got {limit:g}")
    return int(limit * 2**20)


def _make_matcher(args, max_disparity, weights, progress=False, ctx=None, min_disparity=0):
    """A StereoMatcher; pass ``ctx`` (a ClContext) to share one context and its program cache.
    ``max_disparity``: D or "auto"; ``min_disparity``: M (disparities M .. M+D-1)."""
    from ..pipeline import StereoMatcher
    kwargs = dict(max_disparity=max_disparity if max_disparity == "auto" else int(max_disparity),
                  device=ctx if ctx is not None else args.device, cost=args.cost, progress=progress)
    if min_disparity:
        kwargs["min_disparity"] = int(min_disparity)
    if args.cost == "cnn":
        kwargs["weights"] = weights
    kwargs["volume_dtype"] = getattr(args, "volume_dtype", "float32")
    limit = _memory_limit(args)
    if limit is not None:
        kwargs["memory_limit"] = limit
    hyper = _hyperparameters(getattr(args, "hyper", []))
    try:
        return StereoMatcher(**kwargs, **hyper)
    except TypeError as exc:  # unknown hyperparameter name
        raise InputError(f"--set: {exc}") from exc


def _hyperparameters(items) -> dict:
    """``["sgm_pi2=64", "interpolation=code"]`` -> ``{"sgm_pi2": 64, "interpolation": "code"}``."""
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        name, value = name.strip(), value.strip()
        if not sep or not name:
            raise InputError(f"--set expects NAME=VALUE, got {item!r}")
        low = value.lower()
        if low in ("true", "false"):
            out[name] = low == "true"
        elif low in ("none", "null"):
            out[name] = None
        else:
            try:
                out[name] = int(value)
            except ValueError:
                try:
                    out[name] = float(value)
                except ValueError:
                    out[name] = value
    return out


def _check_pair(left, right, max_disparity, weights, names=("left", "right"), min_disparity=0):
    """Clear errors for inputs the pipeline cannot match (:func:`mccnn_cl.validate.check_pair`)."""
    from ..validate import check_pair, patch_size
    check_pair(left, right, max_disparity, patch_size(weights), names, min_disparity=min_disparity)


def _range_request(args):
    """The range asked for: "auto", or (M, D) with D None when not given
    (--disp-range, else --min-disp and --max-disp)."""
    from ..disprange import levels_of, parse_range
    spec = getattr(args, "disp_range", None)
    low = getattr(args, "min_disp", None)
    if spec is not None:
        if args.max_disp is not None or low is not None:
            raise InputError("--disp-range gives the whole range; drop --max-disp and --min-disp (or --disp-range)")
        rng = parse_range(spec)
        return "auto" if rng == "auto" else levels_of(rng)
    return (low or 0, args.max_disp)


def _range_text(lo, hi, auto=None) -> str:
    text = f"disparities {lo}..{hi}"
    if auto is not None:
        text += f" (auto: coarse pass at 1/{auto['scale']} size, {auto['seconds']:.2f} s)"
    return text


def _check_outputs(paths, force, inputs=(), taken=None):
    """Before any work: every output's folder exists and takes files, no output
    is an existing file (unless ``force``) or a folder, none is one of the
    ``inputs`` (even with ``force``), and no two outputs are the same file
    (``taken``: real path -> what claimed it, shared across a batch's pairs)."""
    from ..atomic import check_writable
    taken = {} if taken is None else taken
    ins = {os.path.realpath(f): f for f in inputs if f}
    for p in paths:
        if p is None:
            continue
        d = os.path.dirname(os.path.abspath(p))
        if not os.path.isdir(d):
            raise InputError(f"output folder does not exist: {d}")
        real = os.path.realpath(p)
        if real in ins:
            raise InputError(f"output {p} is the input image {ins[real]}; choose another name")
        if real in taken:
            raise InputError(f"two outputs are the same file: {taken[real]} and {p}; give them different names")
        taken[real] = p
        if os.path.isdir(p):
            raise InputError(f"{p} is a folder, not a file")
        if os.path.exists(p) and not force:
            raise InputError(f"{p} exists; pass --force to overwrite it")
        check_writable(d)


#: Largest disparity a KITTI 16-bit PNG holds (value / 256, value <= 65535).
PNG_MAX_DISPARITY = 65535 / 256


def _check_png_range(out, max_disp, min_disp=0):
    """A .png output holds disparities in [0, 65535/256] only: refuse a range
    that can leave it, before any work (the writer refuses such values too)."""
    if os.path.splitext(out)[1].lower() != ".png":
        return
    if min_disp < 0:
        raise InputError(f"{out}: a KITTI 16-bit PNG cannot store negative disparities (the range starts "
                         f"at {min_disp}); write .pfm or .npy")
    if max_disp - 1 + min_disp > PNG_MAX_DISPARITY:
        raise InputError(f"{out}: a KITTI 16-bit PNG holds disparities 0..{PNG_MAX_DISPARITY:.3f}, but the range "
                         f"reaches {min_disp}..{min_disp + max_disp - 1} (--max-disp {max_disp}); "
                         "write .pfm or .npy instead")


def write_disparity(path, disp) -> None:
    """Write by extension: .pfm (+inf invalid), .png (KITTI 16-bit ×256, 0 invalid), .npy (NaN invalid)."""
    from ..depth import atomic_write
    from ..io import write_kitti_disparity, write_pfm
    ext = os.path.splitext(path)[1].lower()
    d = np.asarray(disp, dtype=np.float32)
    if ext == ".pfm":
        write_pfm(path, np.where(np.isfinite(d), d, np.float32(np.inf)))
    elif ext == ".png":
        # the range fits the PNG (checked before the run), but subpixel
        # enhancement may step a little past its ends: such pixels become
        # invalid (0), said in one line, never clipped to the edge silently
        from ..io import KITTI_MAX_DISPARITY
        with np.errstate(invalid="ignore"):
            out = np.isfinite(d) & ((d < 0) | (d > KITTI_MAX_DISPARITY))
        if out.any():
            print(f"mccnn-cl: warning: {path}: {int(out.sum())} pixels outside 0..{KITTI_MAX_DISPARITY:.3f} px "
                  f"(subpixel steps past the range's ends, {float(d[out].min()):g}..{float(d[out].max()):g}) "
                  "written as invalid (0): a KITTI PNG cannot hold them (.pfm and .npy do)", file=sys.stderr)
            d = np.where(out, np.float32(np.nan), d)
        write_kitti_disparity(path, d)
    elif ext == ".npy":
        def write(tmp):
            with open(tmp, "wb") as f:
                np.save(f, np.where(np.isfinite(d), d, np.float32(np.nan)))
        atomic_write(path, write)
    else:
        raise InputError(f"{path}: unknown disparity format {ext!r}; use one of "
                         f"{', '.join(DISPARITY_FORMATS)}")


def _write_depth(path, depth):
    from ..depth import atomic_write
    from ..io import write_pfm
    if path.endswith(".pfm"):
        write_pfm(path, np.where(np.isfinite(depth), depth, np.float32(np.inf)))
    else:
        def write(tmp):
            with open(tmp, "wb") as f:
                np.save(f, depth)
        atomic_write(path, write)


def _expand(spec, what):
    """Files named by a glob pattern, a folder (its images) or a single file; sorted."""
    if os.path.isdir(spec):
        files = [os.path.join(spec, f) for f in os.listdir(spec)
                 if f.lower().endswith(IMAGE_EXTENSIONS) and os.path.isfile(os.path.join(spec, f))]
    else:
        files = [f for f in glob.glob(spec) if os.path.isfile(f)]
    files.sort()
    if not files:
        raise InputError(f"no {what} images match {spec!r}")
    return files


def _side_outputs(out, args):
    """Paths written next to a disparity file: colour picture, depth, point cloud."""
    stem = os.path.splitext(out)[0]
    color = None
    if args.color is not None:
        color = args.color if args.color else stem + "_color.png"
    depth = ply = None
    if args.calib and not getattr(args, "no_depth", False):
        depth = stem + ("_depth.pfm" if out.lower().endswith(".pfm") else "_depth.npy")
        ply = stem + ".ply"
    return color, depth, ply


CONFIDENCE_FORMATS = (".pfm", ".png", ".npy")
LABEL_FORMATS = (".png", ".npy")


def _confidence_outputs(out, args):
    """Paths of ``--confidence`` and ``--labels`` (None when not asked), extensions checked."""
    stem = os.path.splitext(out)[0]
    paths = []
    for value, default, formats, what in ((args.confidence, "_confidence.pfm", CONFIDENCE_FORMATS, "--confidence"),
                                          (args.labels, "_labels.png", LABEL_FORMATS, "--labels")):
        path = None if value is None else (value or stem + default)
        if path is not None and os.path.splitext(path)[1].lower() not in formats:
            raise InputError(f"{path}: {what} must end in {', '.join(formats)}")
        paths.append(path)
    return paths


def _save_confidence(out, res, args):
    """--confidence: .pfm / .npy float32 in [0, 1], .png 16-bit round(c * 65535);
    --labels: 0 correct, 1 mismatch, 2 occlusion as 8-bit .png or int32 .npy."""
    import cv2

    from ..depth import atomic_write
    from ..io import write_image, write_pfm
    conf_path, labels_path = _confidence_outputs(out, args)
    for path, a in ((conf_path, res.confidence), (labels_path, res.labels)):
        if path is None:
            continue
        ext = os.path.splitext(path)[1].lower()
        if ext == ".pfm":
            write_pfm(path, a.astype(np.float32))
        elif ext == ".npy":
            atomic_write(path, lambda tmp, a=a: np.save(tmp, a))
        elif a is res.labels:
            write_image(path, a.astype(np.uint8))
        else:
            raw = np.round(np.clip(a, 0, 1) * 65535.0).astype(np.uint16)

            def write(tmp, raw=raw, path=path):
                if not cv2.imwrite(tmp, raw):
                    raise InputError(f"{path}: cv2 could not write the PNG")
            atomic_write(path, write)


# -- match -------------------------------------------------------------------

def cmd_match(args):
    from ..io import read_image
    _positive("--max-disp", args.max_disp)
    request = _range_request(args)
    single = args.left is not None or args.right is not None
    batch = args.left_glob is not None or args.right_glob is not None
    pairs_dir = getattr(args, "pairs_dir", None)
    batch = batch or pairs_dir is not None
    if single == batch:
        raise InputError("give either LEFT RIGHT -o OUT, or -l LEFT_GLOB -r RIGHT_GLOB (or --pairs-dir DIR) "
                         "--output-dir DIR")
    distributed = getattr(args, "workers", None) is not None or getattr(args, "scheduler", None) is not None
    if batch and not distributed:
        from ..batch import run_batch
        return run_batch(args)
    if distributed:
        from ..distributed import run as run_distributed
        return run_distributed(args, single)
    calib = None
    if args.calib:
        from ..depth import read_calib
        calib = read_calib(args.calib)
        if not calib.has_depth:  # Middlebury 2001-2006: only width, height, ndisp
            args.no_depth = True
            print(f"mccnn-cl: note: {args.calib} has no focal length/baseline: it gives the disparity range "
                  f"(ndisp={calib.ndisp}); no depth or point cloud is written", file=sys.stderr)
    if single:
        if args.left is None or args.right is None or args.output is None:
            raise InputError("match needs LEFT RIGHT and -o OUT")
        if args.output_dir:
            raise InputError("--output-dir is for batches (-l/-r); use -o for one pair")
        if getattr(args, "resume", False):
            raise InputError("--resume is for batches (-l/-r or --pairs-dir)")
        jobs = [(args.left, args.right, args.output)]
    taken, inputs = {}, [f for job in jobs for f in job[:2]]
    for lp, rp, out in jobs:
        for f in (lp, rp):
            if not os.path.isfile(f):
                raise InputError(f"file not found: {f}")
        if os.path.splitext(out)[1].lower() not in DISPARITY_FORMATS:
            raise InputError(f"{out}: output must end in {', '.join(DISPARITY_FORMATS)}")
        if request != "auto":
            lo, levels = request
            if levels is None:
                levels = calib.ndisp if (calib is not None and calib.ndisp) else 228
            _check_png_range(out, levels, lo or 0)
        color, depth, ply = _side_outputs(out, args)
        if color is not None and not color.lower().endswith((".png", ".jpg", ".jpeg", ".bmp")):
            raise InputError(f"{color}: the colour picture must be a .png/.jpg/.bmp file")
        _check_outputs([out, color, depth, ply, *_confidence_outputs(out, args)], args.force, inputs, taken)

    weights = _load_weights(args)
    from ..opencl.context import ClContext
    matchers, ctx = {}, None
    progress = None
    if batch:
        from tqdm import tqdm
        progress = tqdm(total=len(jobs), unit="pair", desc="matching", disable=None)
    try:
        for lp, rp, out in jobs:
            left_img = read_image(lp)
            right_img = read_image(rp)
            if request == "auto":
                key, min_disp, max_disp = "auto", 0, "auto"
                _check_pair(left_img, right_img, 1, weights, (lp, rp))
            else:
                min_disp, max_disp = request
                if max_disp is None:
                    max_disp = calib.ndisp if (calib is not None and calib.ndisp) else 228
                key = (min_disp, max_disp)
                _check_pair(left_img, right_img, max_disp, weights, (lp, rp), min_disparity=min_disp)
            if key not in matchers:
                if ctx is None:
                    ctx = ClContext(args.device)
                matchers[key] = _make_matcher(args, max_disp, weights, progress=single and _tty(),
                                              ctx=ctx, min_disparity=min_disp)
            t0 = time.perf_counter()
            want = args.confidence is not None or args.labels is not None
            gray_l, gray_r = _gray(left_img), _gray(right_img)
            auto = None
            if request == "auto":
                auto = matchers[key].choose_range(gray_l, gray_r)
                lo, hi = auto["range"]
                if out.lower().endswith(".png"):  # the format holds no negative disparity
                    if auto["found"][0] < 0:  # the scene's own, not the margin's
                        raise InputError(f"{out}: the automatic range {lo}..{hi} holds the pair's negative "
                                         f"disparities (down to {auto['found'][0]:.0f}), which a KITTI 16-bit PNG "
                                         "cannot store; write .pfm or .npy")
                    lo = max(lo, 0)  # only the margin went below 0
            else:
                lo, hi = min_disp, min_disp + max_disp - 1
            range_line = _range_text(lo, hi, auto)
            if auto is not None and progress is not None:
                progress.write(f"{out}: {range_line}")
            res = matchers[key].compute(gray_l, gray_r, confidence=want,
                                        disparity_range=(lo, hi) if auto is not None else None)
            disp = res.disparity if want else res
            seconds = time.perf_counter() - t0
            if want:
                _save_confidence(out, res, args)
            _save_outputs(out, disp, left_img, args, calib, (lo, hi))  # the disparity file last
            fin = np.isfinite(disp)
            levels = f"{hi - lo + 1} disparities" if (lo == 0 and auto is None) else range_line
            msg = (f"{out}: {disp.shape[1]}x{disp.shape[0]}, {levels}, "
                   f"{fin.mean():.1%} valid, {seconds:.2f} s")
            if progress is not None:
                progress.update(1)
                if args.verbose:
                    progress.write(msg)
            else:
                _say(msg)
    finally:
        if progress is not None:
            progress.close()
    if batch:
        _say(f"wrote {len(jobs)} disparity maps to {args.output_dir}")
    return 0


def _tty() -> bool:
    """Progress bars only on a terminal (not in logs or pipes)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def _gray(img):
    from ..evaluation.datasets import to_gray_u8
    return to_gray_u8(img)


def _save_outputs(out, disp, left_img, args, calib, disparity_range):
    from ..io import write_image
    from ..visualize import colorize_with_legend
    color, depth_path, ply = _side_outputs(out, args)
    if color is not None:
        # scale: 0 (or the range's negative minimum) .. the map's largest disparity (the range's
        # maximum would waste most colours on KITTI)
        lo, hi = disparity_range
        fin = disp[np.isfinite(disp)]
        vmax = min(float(fin.max()), hi) if fin.size else hi
        vmin = 0 if lo >= 0 else (max(float(fin.min()), lo) if fin.size else lo)
        write_image(color, colorize_with_legend(disp, vmin, max(vmax, vmin + 1.0)))
    if calib is not None and calib.has_depth:
        from ..depth import disparity_to_depth, point_cloud, write_ply
        _write_depth(depth_path, disparity_to_depth(disp, calib))
        pts, rgb = point_cloud(disp, calib, left_img)
        write_ply(ply, pts, rgb, binary=not args.ply_ascii)
    write_disparity(out, disp)  # last: a pair whose disparity file exists is complete (mccnn_cl.batch)


# -- evaluate ----------------------------------------------------------------

def cmd_evaluate(args):
    from ..evaluation.datasets import discover
    from ..evaluation.scoring import (default_range, evaluate_pair, family_means, format_family_tables, mean_metrics,
                                      training_status)
    _positive("--max-disp", args.max_disp)
    request = _range_request(args)
    refs = discover(args.dataset_dir, args.dataset, labeled=True)  # scores need ground truth
    if args.pairs:
        wanted = [w.strip() for w in args.pairs.split(",") if w.strip()]
        def names(r):  # "Cones", "middlebury/Cones"; MiddEval3 "trainingQ/Motorcycle" also as "Motorcycle"
            return {r.name, r.key, r.name.rsplit("/", 1)[-1]}
        refs = [r for r in refs if names(r) & set(wanted)]
        found = set().union(*(names(r) for r in refs)) if refs else set()
        missing = [w for w in wanted if w not in found]
        if missing:
            raise InputError(f"pairs not found under {args.dataset_dir}: {', '.join(missing)}")
    if not refs:
        raise InputError(f"no stereo pairs with ground truth found under {args.dataset_dir}"
                         + (f" for dataset {args.dataset}" if args.dataset else ""))
    baselines = [b.strip() for b in str(args.baseline).split(",") if b.strip()]
    bad = [b for b in baselines if b not in ("sgbm", "census", "none")]
    if bad or not baselines or ("none" in baselines and len(baselines) > 1):
        raise InputError(f"--baseline: expected a comma-separated list of sgbm, census, or none; got {args.baseline!r}")
    if args.cost == "census" and "census" in baselines:  # the method itself is census: no second run
        baselines.remove("census")
    weights = _load_weights(args)
    meta = weights.meta if weights is not None else None
    from ..opencl.context import ClContext
    results, matchers, census, ctx = [], {}, {}, None
    from tqdm import tqdm
    bar = tqdm(refs, unit="pair", desc="evaluating", disable=None if not args.json else True)
    for ref in bar:
        pair = ref.load()
        if pair.disp is None:
            bar.write(f"{pair.key}: no ground truth, skipped")
            continue
        stated_min, stated_levels = default_range(pair)  # the layout's range (calib.txt), else 0..227
        if request == "auto":
            key, min_disp, max_disp = "auto", 0, "auto"
            _check_pair(pair.left, pair.right, 1, weights, (pair.key + " left", "right"))
        else:
            min_disp = stated_min if args.min_disp is None and args.disp_range is None else request[0]
            max_disp = request[1] or stated_levels
            key = (min_disp, max_disp)
            _check_pair(pair.left, pair.right, max_disp, weights, (pair.key + " left", "right"),
                        min_disparity=min_disp)
        if key not in matchers:
            if ctx is None:
                ctx = ClContext(args.device)
            matchers[key] = _make_matcher(args, max_disp, weights, ctx=ctx, min_disparity=min_disp)
            if "census" in baselines:
                census[key] = _make_matcher(argparse.Namespace(**{**vars(args), "cost": "census", "hyper": []}),
                                            max_disp, None, ctx=ctx, min_disparity=min_disp)
        status = training_status(meta, pair.key, pair.name) if weights is not None else "n/a"
        base_min, base_levels = (stated_min, stated_levels) if request == "auto" else (min_disp, max_disp)
        results.append(evaluate_pair(pair, matchers[key], base_levels,
                                     baseline="sgbm" if "sgbm" in baselines else None,
                                     fill=not args.no_fill, error_maps=args.error_maps, status=status,
                                     min_disparity=base_min,
                                     others={"census": census[key]} if "census" in baselines else None))
    if not results:
        raise InputError("none of the pairs has ground truth")
    mean = mean_metrics(results)
    if args.json:
        doc = {"cost": args.cost, "weights": _weights_label(args), "fill": not args.no_fill,
               "baselines": [b for b in baselines if b != "none"], "pairs": results, "mean": mean,
               "families": family_means(results)}
        _say(json.dumps(_jsonable(doc), indent=2))
    else:
        who = f"MC-CNN ({_weights_label(args)})" if args.cost == "cnn" else "census cost + the MC-CNN stereo method"
        beside = " and ".join({"sgbm": "OpenCV SGBM", "census": "census (cens)"}[b] for b in baselines if b != "none")
        _say(f"{who}" + (f" beside {beside}" if beside else "") + "; errors in % of GT pixels, "
             + ("holes filled as the KITTI devkit does" if not args.no_fill else "holes counted as errors"))
        _say(format_family_tables(results))
        _say("training: whether the weights' metadata lists the pair as a training pair "
             "(held out = not used); n/a for --cost census")
    return 0


def _weights_label(args):
    if args.cost != "cnn":
        return "census cost, no network"
    return os.path.basename(args.weights) if args.weights else "shipped weights"


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, (np.floating, np.integer)):
        return _jsonable(obj.item())
    return obj


# -- devices -----------------------------------------------------------------

def cmd_devices(args):
    from ..opencl.context import list_devices, select_device
    devices = list_devices()
    chosen, reason = select_device(args.device)
    _say("OpenCL devices (P:D indices for --device / PYOPENCL_CTX), in order of preference:")
    for d in devices:
        mark = "*" if d.handle == chosen else " "
        _say(f" {mark} {d.platform_index}:{d.device_index}  {d}")
    name = next((str(d) for d in devices if d.handle == chosen), chosen.name.strip())
    _say(f"would use: {name}")
    _say(f"because:   {reason}")
    from .tune import describe_choices
    for line in describe_choices(chosen):
        _say(line)
    workers = getattr(args, "workers", None)
    if workers is not None:
        _positive("--workers", workers)
        from ..distributed import worker_device
        for i in range(workers):
            info, why = worker_device(args.device, i)
            _say(f"worker {i}: {info.platform_index}:{info.device_index}  {info}  ({why})")
    return 0
