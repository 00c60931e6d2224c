"""Input checks shared by the command line and :class:`~mccnn_cl.pipeline.StereoMatcher`.

One place says what pair of images and which disparity range the method can
match, so ``mccnn-cl match`` (on the images as read, before any OpenCL work)
and ``StereoMatcher.compute`` (on the gray images) reject the same inputs with
the same one-line :class:`~mccnn_cl.errors.InputError`; the network costs
check their own inputs here too (:func:`check_cost_inputs`: one gray image
each, finite pixels, at least the network's patch).  The smallest image is
the matching cost's patch (9 x 9 for census and the paper's networks; a
network's own ``patch_size`` when larger); a range from 0 must be smaller
than the image width (disparities 0 .. D-1 need a right pixel x - d), one
from M != 0 must leave some pixel a match (:func:`check_pair`).
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .imageops import unit_float64

#: The paper's network patch and the census window: the smallest image.
PATCH = 9


def patch_size(weights=None) -> int:
    """The patch a matching cost needs: the network's (``weights.patch_size``), at least :data:`PATCH`."""
    return max(int(weights.patch_size) if weights is not None else 1, PATCH)


def check_disparity_range(max_disparity) -> int:
    """D as an int: an integer >= 1 (not a bool)."""
    if isinstance(max_disparity, (bool, np.bool_)) or not isinstance(max_disparity, (int, np.integer)):
        raise InputError(f"max_disparity must be an integer, not {max_disparity!r}")
    if max_disparity < 1:
        raise InputError(f"max_disparity must be >= 1, not {max_disparity}")
    return int(max_disparity)


def _same_size(left, right, names=("left", "right")) -> tuple:
    """(H, W) of two images of the same size (first two axes)."""
    (h, w), (hr, wr) = np.shape(left)[:2], np.shape(right)[:2]
    if (h, w) != (hr, wr):
        raise InputError(f"{names[0]} ({w}x{h}) and {names[1]} ({wr}x{hr}) images differ in size")
    return h, w


def as_image(img, name: str, channels: int, patch: int) -> np.ndarray:
    """One input image of a network cost, checked: numeric, H x W (or H x W x
    ``channels``), at least ``patch`` x ``patch``, finite; returned as float64 H x W x C
    on :func:`~mccnn_cl.imageops.unit_float64`'s scale (that of ``stats=``)."""
    try:
        a = np.asarray(img)
    except Exception as exc:  # noqa: BLE001 - anything numpy cannot take
        raise InputError(f"{name} image: not an array ({exc})") from exc
    if a.dtype.kind not in "buif":
        raise InputError(f"{name} image: dtype {a.dtype} is not numeric")
    if a.ndim == 2:
        a = a[:, :, None]
    elif a.ndim != 3:
        raise InputError(f"{name} image: expected a 2-D gray image (H x W), got shape {a.shape}")
    if a.shape[2] != channels:
        raise InputError(f"{name} image has {a.shape[2]} channels, the network expects {channels}"
                         + (" (a 2-D gray image)" if channels == 1 else ""))
    if a.shape[0] < patch or a.shape[1] < patch:
        raise InputError(f"{name} image is {a.shape[0]}x{a.shape[1]}, smaller than the network's "
                         f"{patch}x{patch} patch")
    a = unit_float64(a)  # the scale of image_stats: uint8 / 255, uint16 / 65535 (as to_gray)
    if not np.isfinite(a).all():
        raise InputError(f"{name} image contains NaN or infinite pixels")
    return a


def check_cost_inputs(left, right, max_disparity, channels: int, patch: int) -> tuple:
    """A network cost's inputs (:func:`as_image` each, same size, D by
    :func:`check_disparity_range`); returns (L, R, D, h, w), h x w the volume's
    domain (the patch centres).  D may reach the width: those cells are NaN."""
    L = as_image(left, "left", channels, patch)
    R = as_image(right, "right", channels, patch)
    _same_size(L, R)
    D = check_disparity_range(max_disparity)
    return L, R, D, L.shape[0] - patch + 1, L.shape[1] - patch + 1


def check_pair(left, right, max_disparity: int, patch: int = PATCH, names=("left", "right"),
               min_disparity: int = 0, range_name: str | None = None) -> None:
    """Clear errors for a pair the method cannot match with ``max_disparity`` levels.

    ``left``, ``right``: arrays H x W or H x W x C (only the first two axes are
    looked at); ``patch``: the matching cost's patch side (see :func:`patch_size`);
    ``names``: what to call the two images in the messages (file names);
    ``min_disparity``: M, the range being M .. M + max_disparity - 1.  With
    M >= 0 the range must be smaller than the image width (disparities 0 .. D-1
    need a right pixel x - d); with M < 0 the method works on a frame
    W - M wide (:mod:`mccnn_cl.disprange`), so D may exceed W, but the largest
    disparity M + D - 1 must stay below W - 1; with M != 0
    :func:`mccnn_cl.disprange.check_range` also holds (some pixel must have a match).
    ``range_name``: how the caller gave the range, for the message (default
    "max_disparity, --max-disp")."""
    h, w = _same_size(left, right, names)
    patch = max(int(patch), PATCH)
    if h < patch or w < patch:
        raise InputError(f"image {w}x{h} is smaller than the {patch}x{patch} patch the matching cost needs")
    if min_disparity >= 0 and max_disparity >= w:
        raise InputError(f"disparity range {max_disparity} ({range_name or 'max_disparity, --max-disp'}) is not "
                         f"smaller than the image width {w}")
    top = min_disparity + max_disparity - 1
    if min_disparity < 0 and top >= w - 1:
        # the working frame is W - M wide, so D may exceed W; levels d >= W - 1 would match no pixel (as
        # D >= W does from 0)
        raise InputError(f"disparities {min_disparity}..{top} ({range_name or '--min-disp, --max-disp'}) reach "
                         f"the image width {w}: no pixel has a match at {w - 1} or more; the largest must be "
                         f"below {w - 1}")
    if min_disparity:
        from .disprange import check_range
        check_range(min_disparity, max_disparity, w, patch)


#: Valid range of every numeric :class:`~mccnn_cl.pipeline.Hyperparameters`
#: field: name -> (integer?, lower bound, bound included?).  Penalties,
#: thresholds and counts may be 0; divisors and sigma must be positive.
#: ``blur_radius`` may also be None (ceil(3 sigma)); ``median_size`` must be odd too.
HYPERPARAMETER_RANGES = {
    "cbca_eta": (True, 0, True), "cbca_tau": (False, 0.0, True),
    "cbca_iterations": (True, 0, True), "cbca_iterations_after": (True, 0, True),
    "sgm_pi1": (False, 0.0, True), "sgm_pi2": (False, 0.0, True), "sgm_tau_so": (False, 0.0, True),
    "sgm_q1": (False, 0.0, False), "sgm_q2": (False, 0.0, False), "sgm_v": (False, 0.0, False),
    "lr_threshold": (False, 0.0, True), "subpixel_min_denominator": (False, 0.0, True),
    "median_size": (True, 1, True), "blur_sigma": (False, 0.0, False), "blur_tau": (False, 0.0, True),
    "blur_radius": (True, 0, True),
}


#: Upper bounds, name -> (largest value, why).  Each comes from what the
#: kernels can hold: arms are stored as bytes (``stages.cross.ARM_LIMIT``), the
#: median window sorts in a fixed private array (``stages.refine.MEDIAN_MAX_SIZE``),
#: integer kernel arguments are 32-bit, and every float reaches the kernels
#: as a float32 that penalties, divisors and thresholds combine with cost
#: sums: :data:`FLOAT_MAX` (and :data:`DIVISOR_MIN` for the divisors) keeps
#: P / (q1 q2 v) and the path sums finite in float32.
FLOAT_MAX = 1e6
DIVISOR_MIN = 1e-6
INT32_MAX = 2 ** 31 - 1


def hyperparameter_maxima() -> dict:
    """name -> (largest accepted value, the kernel bound it comes from); see :data:`FLOAT_MAX`."""
    from .stages.cross import ARM_LIMIT
    from .stages.refine import MEDIAN_MAX_SIZE

    out = {name: (FLOAT_MAX, "float32 kernel arithmetic") if not integer else (INT32_MAX, "32-bit kernel argument")
           for name, (integer, _, _) in HYPERPARAMETER_RANGES.items()}
    out["cbca_eta"] = (ARM_LIMIT + 1, f"cross arms are stored as bytes (arms <= {ARM_LIMIT})")
    out["median_size"] = (MEDIAN_MAX_SIZE, f"the median kernel sorts a fixed {MEDIAN_MAX_SIZE}x{MEDIAN_MAX_SIZE} "
                                           "private array")
    return out


#: Divisors and widths that must stay away from 0 in float32 (:data:`DIVISOR_MIN`).
POSITIVE_FLOATS = ("sgm_q1", "sgm_q2", "sgm_v", "blur_sigma")


def check_number(name: str, value, integer: bool, low, inclusive: bool) -> None:
    """One field against its range: a real number (an integer when ``integer``), finite, >= / > ``low``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{name} must be a number, not {value!r}")
    if not np.isfinite(value):
        raise InputError(f"{name} must be finite, not {value}")
    if integer and int(value) != value:
        raise InputError(f"{name} must be an integer, not {value}")
    if not (value >= low if inclusive else value > low):
        raise InputError(f"{name} must be {'>=' if inclusive else '>'} {low}, not {value}")


def check_hyperparameters(params) -> None:
    """Every numeric field of a Hyperparameters in its range (:data:`HYPERPARAMETER_RANGES`,
    :func:`hyperparameter_maxima`): the one check behind ``Hyperparameters`` (the
    API), ``--set`` (the command line) and a weights file's ``stereo`` settings."""
    maxima = hyperparameter_maxima()
    for name, (integer, low, inclusive) in HYPERPARAMETER_RANGES.items():
        value = getattr(params, name)
        if name == "blur_radius" and value is None:
            continue
        check_number(name, value, integer, low, inclusive)
        high, why = maxima[name]
        if value > high:
            raise InputError(f"{name} must be <= {high:g} ({why}), not {value}")
        if name in POSITIVE_FLOATS and value < DIVISOR_MIN:
            raise InputError(f"{name} must be >= {DIVISOR_MIN:g} (a float32 divisor), not {value}")
    if int(params.median_size) % 2 == 0:
        raise InputError(f"median_size must be a positive odd number, not {params.median_size}")

