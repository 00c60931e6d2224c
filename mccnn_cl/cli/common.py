"""What the command line's commands share: loading weights and settings,
making a matcher, checking outputs before any work, writing disparity maps and
their side files (``match``, its batches on one process or on Dask)."""

from __future__ import annotations

import glob
import math
import os
import sys

import numpy as np

from ..errors import InputError, WeightsError

DISPARITY_FORMATS = (".pfm", ".png", ".npy")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp", ".tif", ".tiff", ".webp")


# -- helpers ---------------------------------------------------------------

def _say(*args):
    print(*args, flush=True)


def counted(n: int, one: str, many: str | None = None) -> str:
    """"1 kernel build", "3 kernel builds": ``n`` and the noun in its number
    (``many`` for an irregular plural, else ``one`` + "s")."""
    return f"{n} {one if n == 1 else (many or one + 's')}"


def _read_calibration(args):
    """``--calib`` parsed (None without it).  A file without focal length and
    baseline (Middlebury 2001-2006: width, height, ndisp) gives the range only:
    a note, and ``args.no_depth`` set so that no depth or point cloud is asked
    (one pair, a batch, or on Dask alike)."""
    if not args.calib:
        return None
    from ..depth import read_calib
    calib = read_calib(args.calib)
    if not calib.has_depth:
        args.no_depth = True
        print(f"mccnn-cl: note: {args.calib} has no focal length/baseline: it gives the disparity range "
              f"(ndisp={calib.ndisp}); no depth or point cloud is written", file=sys.stderr)
    return calib


def _check_calib_size(calib, img, image_path, calib_path) -> None:
    """Warn (stderr, one line) when a calibration file that states an image size (Middlebury /
    MiddEval3 / ETH3D ``width`` and ``height``, KITTI ``S_rect``) states another than this
    image's: for a resized image the disparity range, depth and point cloud would be wrong with no
    other sign.  A warning, not an error: a crop keeps focal length and baseline (its depth is
    right, its points are shifted by the crop's offset)."""
    if calib is None or calib.width is None or calib.height is None:
        return
    h, w = img.shape[:2]
    if (calib.width, calib.height) != (w, h):
        print(f"mccnn-cl: warning: {calib_path} is for {calib.width}x{calib.height} images, {image_path} is "
              f"{w}x{h}: for a resized image give the calibration of its resolution (focal length, principal "
              "point, doffs and ndisp scale with it); a crop's depth is right, its points shifted",
              file=sys.stderr)


def _positive(name, value):
    if value is not None and value < 1:
        raise InputError(f"{name} must be >= 1, got {value}")
    return value


def parse_size(text, parts, example, least=1, what=""):
    """An "x"-separated size of ``parts`` integers (``--size 1242x375``), each >= ``least``;
    InputError naming ``example`` (and ``what`` the parts mean) otherwise."""
    try:
        size = tuple(int(v) for v in str(text).lower().split("x"))
    except ValueError:
        size = ()
    if len(size) != parts or min(size) < least:
        raise InputError(f"--size must look like {example}{f' ({what})' if what else ''}, "
                         f"integers >= {least}, got {text!r}")
    return size


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
    (:func:`mccnn_cl.hyperparameters.check_settings`: the checks StereoMatcher makes)."""
    from ..hyperparameters import check_settings
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
    """``--set`` values: :func:`mccnn_cl.hyperparameters.parse_settings` (one parser for every command)."""
    from ..hyperparameters import parse_settings

    return parse_settings(items, option="--set")


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
        passes = (f"passes at 1/{auto['scale']} and 1/{auto['check_scale']}" if auto.get("check")
                  else f"pass at 1/{auto['scale']}")
        text += f" (auto: coarse {passes} size, {auto['seconds']:.2f} s)"
    return text


def _auto_output_range(out, auto):
    """The range to search for ``out`` given the automatic range's report: a
    KITTI 16-bit PNG holds no negative disparity, so its range starts at 0 at
    the lowest (only the margin went below 0), and a pair whose own disparities
    are negative is refused for it (InputError)."""
    lo, hi = auto["range"]
    if str(out).lower().endswith(".png"):
        if auto["found"][0] < 0:  # the scene's own, not the margin's
            raise InputError(f"{out}: the automatic range {lo}..{hi} holds the pair's negative "
                             f"disparities (down to {auto['found'][0]:.0f}), which a KITTI 16-bit PNG "
                             "cannot store; write .pfm or .npy")
        lo = max(lo, 0)
    return lo, hi


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


def _writing(path, write, *args) -> None:
    """``write(*args)``, an OSError of it naming ``path`` (the file being written) when it
    names no file or only the writer's temporary file: so that a full disk or a read-only
    folder says which output it stopped (:func:`mccnn_cl.batch.storage_stop`)."""
    from ..atomic import PREFIX
    try:
        write(*args)
    except OSError as exc:
        if exc.filename is None or os.path.basename(os.fsdecode(exc.filename)).startswith(PREFIX):
            exc.filename = os.fspath(path)
        raise


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
            _writing(path, write_pfm, path, a.astype(np.float32))
        elif ext == ".npy":
            _writing(path, atomic_write, path, lambda tmp, a=a: np.save(tmp, a))
        elif a is res.labels:
            _writing(path, write_image, path, a.astype(np.uint8))
        else:
            raw = np.round(np.clip(a, 0, 1) * 65535.0).astype(np.uint16)

            def write(tmp, raw=raw, path=path):
                if not cv2.imwrite(tmp, raw):
                    raise InputError(f"{path}: cv2 could not write the PNG")
            _writing(path, atomic_write, path, write)


def _tty() -> bool:
    """Progress bars only on a terminal (not in logs or pipes)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def _builds_note(ctx) -> None:
    """On a terminal, after a command: say that this process built OpenCL programs from
    source (each fresh process repeats it until ``mccnn-cl tune`` stores the binaries)."""
    from ..opencl import binaries

    if ctx is None or not ctx.builds or not binaries.enabled() or not _tty():
        return
    print(f"mccnn-cl: note: this run built {counted(ctx.builds, 'OpenCL program')} from source (making "
          f"programs took {ctx.build_seconds:.1f} s); `mccnn-cl tune` stores the default methods' binaries, "
          "which later runs load in milliseconds (docs/tuning.md)", file=sys.stderr)


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
        _writing(color, write_image, color, colorize_with_legend(disp, vmin, max(vmax, vmin + 1.0)))
    if calib is not None and calib.has_depth:
        from ..depth import disparity_to_depth, point_cloud, write_ply
        _writing(depth_path, _write_depth, depth_path, disparity_to_depth(disp, calib))
        pts, rgb = point_cloud(disp, calib, left_img)
        _writing(ply, write_ply, ply, pts, rgb, not args.ply_ascii)
    _writing(out, write_disparity, out, disp)  # last: a pair whose disparity file exists is complete (mccnn_cl.batch)
