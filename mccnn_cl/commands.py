"""Bodies of ``mccnn-cl match``, ``evaluate`` and ``devices`` and the helpers
every sub-command shares (the parser and the dispatch live in :mod:`mccnn_cl.cli`).

:func:`cmd_match` writes one pair or a batch (disparity by extension, colour
picture, depth and point cloud with ``--calib``, confidence and labels);
:func:`cmd_evaluate` scores a dataset beside OpenCV SGBM; :func:`cmd_devices`
lists OpenCL devices and the choice.  The shared helpers -- :func:`_load_weights`
(weights checked before any OpenCL work), :func:`_make_matcher` (options and
``--set`` hyperparameters to a StereoMatcher), :func:`_check_outputs`,
:func:`_gray`, :func:`_tty`, :func:`_say` -- are also used by
:mod:`mccnn_cl.bench` and :mod:`mccnn_cl.demo_cmd`.  Bad input raises
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

from .errors import InputError, WeightsError

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
        return None
    from .weights import default_weights_path, resolve
    if args.weights is None and not os.path.exists(default_weights_path()):
        raise WeightsError(f"the shipped weights are not installed ({default_weights_path()}); "
                           "pass --weights FILE or use --cost census")
    return resolve(args.weights)  # .npz, .t7/.pt (converted), or a shipped model's name


def _make_matcher(args, max_disparity, weights, progress=False, ctx=None):
    """A StereoMatcher; pass ``ctx`` (a ClContext) to share one context and its program cache."""
    from .pipeline import StereoMatcher
    kwargs = dict(max_disparity=int(max_disparity), device=ctx if ctx is not None else args.device,
                  cost=args.cost, progress=progress)
    if args.cost == "cnn":
        kwargs["weights"] = weights
    kwargs["volume_dtype"] = getattr(args, "volume_dtype", "float32")
    limit = getattr(args, "memory_limit", None)
    if limit is not None:
        if not limit > 0:
            raise InputError(f"--memory-limit must be a positive number of MiB, got {limit:g}")
        kwargs["memory_limit"] = int(limit * 2**20)
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


def _check_pair(left, right, max_disparity, weights, names=("left", "right")):
    """Clear errors for inputs the pipeline cannot match (:func:`mccnn_cl.validate.check_pair`)."""
    from .validate import check_pair, patch_size
    check_pair(left, right, max_disparity, patch_size(weights), names)


def _check_outputs(paths, force):
    for p in paths:
        if p is None:
            continue
        d = os.path.dirname(os.path.abspath(p))
        if not os.path.isdir(d):
            raise InputError(f"output folder does not exist: {d}")
        if os.path.exists(p) and not force:
            raise InputError(f"{p} exists; pass --force to overwrite it")
        if os.path.isdir(p):
            raise InputError(f"{p} is a folder, not a file")


def write_disparity(path, disp) -> None:
    """Write by extension: .pfm (+inf invalid), .png (KITTI 16-bit ×256, 0 invalid), .npy (NaN invalid)."""
    from .depth import atomic_write
    from .io import write_kitti_disparity, write_pfm
    ext = os.path.splitext(path)[1].lower()
    d = np.asarray(disp, dtype=np.float32)
    if ext == ".pfm":
        write_pfm(path, np.where(np.isfinite(d), d, np.float32(np.inf)))
    elif ext == ".png":
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
    from .depth import atomic_write
    from .io import write_pfm
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
    if args.calib:
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

    from .depth import atomic_write
    from .io import write_image, write_pfm
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
    from .io import read_image
    _positive("--max-disp", args.max_disp)
    single = args.left is not None or args.right is not None
    batch = args.left_glob is not None or args.right_glob is not None
    if single == batch:
        raise InputError("give either LEFT RIGHT -o OUT, or -l LEFT_GLOB -r RIGHT_GLOB --output-dir DIR")
    calib = None
    if args.calib:
        from .depth import read_calib
        calib = read_calib(args.calib)
        calib.require_depth()
    if single:
        if args.left is None or args.right is None or args.output is None:
            raise InputError("match needs LEFT RIGHT and -o OUT")
        if args.output_dir:
            raise InputError("--output-dir is for batches (-l/-r); use -o for one pair")
        jobs = [(args.left, args.right, args.output)]
    else:
        if args.left_glob is None or args.right_glob is None or args.output_dir is None:
            raise InputError("a batch needs -l LEFT_GLOB, -r RIGHT_GLOB and --output-dir DIR")
        if args.output:
            raise InputError("-o is for one pair; a batch writes into --output-dir")
        if args.color:
            raise InputError("in a batch, --color takes no file name (pictures go next to each output)")
        if args.confidence or args.labels:
            raise InputError("in a batch, --confidence and --labels take no file name (maps go next to each output)")
        lefts, rights = _expand(args.left_glob, "left"), _expand(args.right_glob, "right")
        if len(lefts) != len(rights):
            raise InputError(f"{len(lefts)} left but {len(rights)} right images; they are paired "
                             "by sorted order and must be as many")
        os.makedirs(args.output_dir, exist_ok=True)
        ext = "." + args.format
        jobs, seen = [], set()
        for lp, rp in zip(lefts, rights):
            stem = os.path.splitext(os.path.basename(lp))[0]
            if stem in seen:
                raise InputError(f"two left images are named {stem}; outputs would collide")
            seen.add(stem)
            jobs.append((lp, rp, os.path.join(args.output_dir, stem + ext)))
    for lp, rp, out in jobs:
        for f in (lp, rp):
            if not os.path.isfile(f):
                raise InputError(f"file not found: {f}")
        if os.path.splitext(out)[1].lower() not in DISPARITY_FORMATS:
            raise InputError(f"{out}: output must end in {', '.join(DISPARITY_FORMATS)}")
        color, depth, ply = _side_outputs(out, args)
        if color is not None and not color.lower().endswith((".png", ".jpg", ".jpeg", ".bmp")):
            raise InputError(f"{color}: the colour picture must be a .png/.jpg/.bmp file")
        _check_outputs([out, color, depth, ply, *_confidence_outputs(out, args)], args.force)

    weights = _load_weights(args)
    from .cl import ClContext
    matchers, ctx = {}, None
    progress = None
    if batch:
        from tqdm import tqdm
        progress = tqdm(total=len(jobs), unit="pair", desc="matching", disable=None)
    try:
        for lp, rp, out in jobs:
            left_img = read_image(lp)
            right_img = read_image(rp)
            max_disp = args.max_disp
            if max_disp is None:
                max_disp = calib.ndisp if (calib is not None and calib.ndisp) else 228
            _check_pair(left_img, right_img, max_disp, weights, (lp, rp))
            if max_disp not in matchers:
                if ctx is None:
                    ctx = ClContext(args.device)
                matchers[max_disp] = _make_matcher(args, max_disp, weights, progress=single and _tty(),
                                                   ctx=ctx)
            t0 = time.perf_counter()
            want = args.confidence is not None or args.labels is not None
            res = matchers[max_disp].compute(_gray(left_img), _gray(right_img), confidence=want)
            disp = res.disparity if want else res
            seconds = time.perf_counter() - t0
            _save_outputs(out, disp, left_img, args, calib, max_disp)
            if want:
                _save_confidence(out, res, args)
            fin = np.isfinite(disp)
            msg = (f"{out}: {disp.shape[1]}x{disp.shape[0]}, {max_disp} disparities, "
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
    from .datasets import to_gray
    return to_gray(img)


def _save_outputs(out, disp, left_img, args, calib, max_disp):
    from .io import write_image
    from .visualize import colorize_with_legend
    write_disparity(out, disp)
    color, depth_path, ply = _side_outputs(out, args)
    if color is not None:
        # scale: 0 .. the map's largest disparity (the range D - 1 would waste most colours on KITTI)
        fin = disp[np.isfinite(disp)]
        vmax = min(float(fin.max()), max_disp - 1) if fin.size else max_disp - 1
        write_image(color, colorize_with_legend(disp, 0, max(vmax, 1.0)))
    if calib is not None:
        from .depth import disparity_to_depth, point_cloud, write_ply
        _write_depth(depth_path, disparity_to_depth(disp, calib))
        pts, rgb = point_cloud(disp, calib, left_img)
        write_ply(ply, pts, rgb, binary=not args.ply_ascii)


# -- evaluate ----------------------------------------------------------------

def cmd_evaluate(args):
    from .datasets import discover
    from .evaluate import (default_max_disparity, evaluate_pair, family_means, format_family_tables, mean_metrics,
                           training_status)
    _positive("--max-disp", args.max_disp)
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
    from .cl import ClContext
    results, matchers, census, ctx = [], {}, {}, None
    from tqdm import tqdm
    bar = tqdm(refs, unit="pair", desc="evaluating", disable=None if not args.json else True)
    for ref in bar:
        pair = ref.load()
        if pair.disp is None:
            bar.write(f"{pair.key}: no ground truth, skipped")
            continue
        max_disp = args.max_disp or default_max_disparity(pair)
        _check_pair(pair.left, pair.right, max_disp, weights, (pair.key + " left", "right"))
        if max_disp not in matchers:
            if ctx is None:
                ctx = ClContext(args.device)
            matchers[max_disp] = _make_matcher(args, max_disp, weights, ctx=ctx)
            if "census" in baselines:
                census[max_disp] = _make_matcher(argparse.Namespace(**{**vars(args), "cost": "census",
                                                                       "hyper": []}),
                                                 max_disp, None, ctx=ctx)
        status = training_status(meta, pair.key, pair.name) if weights is not None else "n/a"
        results.append(evaluate_pair(pair, matchers[max_disp], max_disp,
                                     baseline="sgbm" if "sgbm" in baselines else None,
                                     fill=not args.no_fill, error_maps=args.error_maps, status=status,
                                     others={"census": census[max_disp]} if "census" in baselines else None))
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
    from .cl import list_devices, select_device
    devices = list_devices()
    chosen, reason = select_device(args.device)
    _say("OpenCL devices (P:D indices for --device / PYOPENCL_CTX), in order of preference:")
    for d in devices:
        mark = "*" if d.handle == chosen else " "
        _say(f" {mark} {d.platform_index}:{d.device_index}  {d}")
    name = next((str(d) for d in devices if d.handle == chosen), chosen.name.strip())
    _say(f"would use: {name}")
    _say(f"because:   {reason}")
    return 0
