"""Image conversions shared by inference, training and the tools: one of each.

* :func:`luminance`: a gray or colour (BGR/BGRA, as cv2 reads) image to H x W
  gray in the input's own type (cv2's 0.299 R + 0.587 G + 0.114 B).
* :func:`to_gray`: the stereo method's input, gray float32 in [0, 1]
  (uint8 / 255, uint16 / 65535, float as is: finite and in [0, 1]; either
  byte order).
* :func:`standardise`: the per-image standardisation the networks see,
  (I - mean(I)) / std(I) with mean and std over the whole image in float64
  and the result in float32; a constant image gives zeros.  Integer images
  are first brought to [0, 1] exactly as :func:`to_gray` does, so training
  (which standardises the uint8 gray images it reads) and inference (which
  standardises the matcher's [0, 1] input) get the same values, bit for bit.
* :func:`unit_float64`: the values :func:`standardise` and :func:`image_stats`
  work on (integer images brought to [0, 1] as :func:`to_gray` does, other
  types as they are), in float64.  Whatever hands an image to
  :func:`standardise` together with ``stats`` of :func:`image_stats` must
  give it on this scale (the network costs' input check,
  :func:`mccnn_cl.validate.as_image`), or the statistics do not match the
  pixels: a uint8 image taken as 0 .. 255 against a mean and std of 0 .. 1.
"""

from __future__ import annotations

import os
import sys

import cv2
import numpy as np

from .errors import InputError

_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def user_stacklevel() -> int:
    """The ``stacklevel`` for :func:`warnings.warn`, called from the function
    that warns, that names the first caller outside this package: the user's
    line, whether it called :func:`to_gray` itself or went through
    ``StereoMatcher.compute`` and the helpers in between."""
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    return level


def native(a: np.ndarray) -> np.ndarray:
    """``a`` in the machine's byte order (a big-endian ``'>u2'`` image as uint16;
    cv2 and the dtype checks take native types only)."""
    if not a.dtype.isnative:
        return a.astype(a.dtype.newbyteorder("="))
    return a

#: Divisor bringing each integer dtype to [0, 1].
_UNIT_SCALE = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}


def luminance(img, name: str = "image") -> np.ndarray:
    """H x W gray in the input's own dtype (native byte order) from H x W, H x W x 1, or H x W x 3/4 (BGR/BGRA)."""
    a = native(np.asarray(img))
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)):
        raise InputError(f"{name} image: expected H x W (gray) or H x W x 3/4 (BGR/BGRA), got shape {a.shape}")
    if a.ndim == 3:  # luminance weights 0.299 R + 0.587 G + 0.114 B, in the input's own type
        a = cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    return a


#: A uint16 image whose largest pixel is below this holds at most 12
#: significant bits: likely a 10/12-bit sensor's data (see :func:`to_gray`).
LOW_BITS_BELOW = 4096


def to_gray(img, name: str = "image", bit_depth: int | None = None) -> np.ndarray:
    """Gray float32 in [0, 1] (module docstring); ``name`` goes into the error messages.
    Float pixels are checked before the colour conversion, integer ones converted
    in their own type (cv2 rounds) and then scaled.

    ``bit_depth``: significant bits of an integer image (e.g. 12 for a 12-bit
    sensor's data stored as uint16): pixels are divided by 2**bit_depth - 1
    instead of the type's maximum (a pixel above that is an InputError).
    Without it a uint16 image whose pixels all stay below 4096 gets an
    :class:`~mccnn_cl.errors.InputWarning`: scaled by 65535 it would fill
    [0, 1/16] only, and the [0, 1]-scale thresholds (cbca_tau, sgm_tau_so,
    blur_tau) would then compare the wrong contrast."""
    a = native(np.asarray(img))
    if a.size == 0:
        raise InputError(f"{name} image is empty (shape {a.shape})")
    if bit_depth is not None:
        if a.dtype not in _UNIT_SCALE:
            raise InputError(f"{name} image: bit_depth is for uint8/uint16 images, not {a.dtype}")
        bits = 8 * a.dtype.itemsize
        if isinstance(bit_depth, (bool, np.bool_)) or not isinstance(bit_depth, (int, np.integer)) \
                or not 1 <= bit_depth <= bits:
            raise InputError(f"bit_depth must be an integer in 1..{bits} for a {a.dtype} image, not {bit_depth!r}")
        top = int(a.max())
        if top > 2 ** int(bit_depth) - 1:
            raise InputError(f"{name} image has a pixel of {top}, more than {bit_depth} bits hold "
                             f"({2 ** int(bit_depth) - 1})")
        scale = float(2 ** int(bit_depth) - 1)
    elif a.dtype in _UNIT_SCALE:
        scale = _UNIT_SCALE[a.dtype]
        if a.dtype == np.uint16 and int(a.max()) < LOW_BITS_BELOW:
            import warnings

            from .errors import InputWarning
            warnings.warn(f"{name} image is uint16 but its largest pixel is {int(a.max())} (< 4096): if it "
                          "holds 12-bit (or fewer) data, pass bit_depth=12 (or the sensor's bits); scaled by "
                          "65535 it uses 1/16 of [0, 1] or less", InputWarning, stacklevel=user_stacklevel())
    elif a.dtype.kind == "f":
        a = a.astype(np.float32)
        if not np.isfinite(a).all():
            raise InputError(f"{name} image contains NaN or infinite pixels")
        if a.size and (a.min() < 0 or a.max() > 1):
            raise InputError(f"{name} image: float pixels must lie in [0, 1], found [{a.min():g}, {a.max():g}]")
        scale = 1.0
    else:
        raise InputError(f"{name} image: dtype {a.dtype} not supported (uint8, uint16 or float in [0, 1])")
    return _scaled(luminance(a, name), scale)


def _scaled(a: np.ndarray, scale: float) -> np.ndarray:
    return (a.astype(np.float32) / np.float32(scale)).astype(np.float32)


def standardise(img, stats=None) -> np.ndarray:
    """(I - mean(I)) / std(I), float32, stats in float64 over all pixels and
    channels; std 0 divides by 1 (module docstring).  ``stats``: the
    ``(mean, std)`` to use instead (:func:`image_stats` of another image, e.g.
    the real image a padded one was made from), on the scale of
    :func:`unit_float64` (``img`` is brought to it here)."""
    a = unit_float64(img)
    mean, std = image_stats(a) if stats is None else stats
    return ((a - mean) / std).astype(np.float32)


def unit_float64(img) -> np.ndarray:
    """``img`` as float64 on the scale :func:`standardise` and :func:`image_stats`
    use: uint8 / 255 and uint16 / 65535 in float32 first (as :func:`to_gray`,
    so an integer image and its :func:`to_gray` give the same values, bit for
    bit), any other type's values as they are.  Idempotent on its own output."""
    a = native(np.asarray(img))
    if a.dtype in _UNIT_SCALE:  # as to_gray scales them
        a = _scaled(a, _UNIT_SCALE[a.dtype])
    return np.asarray(a, dtype=np.float64)


def image_stats(img) -> tuple:
    """``(mean, std)`` that :func:`standardise` divides ``img`` by (std 0 -> 1),
    over :func:`unit_float64` of ``img``."""
    a = unit_float64(img)
    mean = a.mean()
    std = a.std()
    if not std > 0:
        std = 1.0
    return mean, std
