"""Disparity ranges that do not start at 0, and the automatic range.

A range is ``M .. M + D - 1`` (``min_disparity`` M, negative allowed; D
levels, as OpenCV's ``minDisparity`` / ``numDisparities``).  The stereo
method's stages only know levels ``d' = 0 .. D-1`` and the invalid cells
``x - d' < 0`` (kernels/common.h), so a range with M != 0 runs in a *working
frame* (:class:`RangeFrame`) where that is again true:

* the left image moved right by ``p = -M`` columns, the right one kept, both
  of width ``W - M``: for M < 0 the left image gets p columns of padding on
  the left and the right image p on the right; for M > 0 the left image's
  first M and the right image's last M columns are dropped (they have no match
  in the range: x - d < 0 for every d >= M, resp. x + d >= W);
* working cell (d', x') compares left pixel x = x' - p with right pixel
  x' - d' = x - d, d = d' + M: every cell with both pixels real is the cell
  of the real pair, and ``x' - d' < 0`` is exactly ``x - d < 0``;
* cells whose left or right pixel is padding (M < 0 only) get the cost
  :data:`CEILING` (``kernels/range.cl``; every cost is <= 1), the images the
  cross arms and SGM compare hold :data:`SENTINEL` there (an arm stops at the
  padding; SGM sees an edge);
* the networks standardise the padded images with the real images' mean and
  std (``stats``), so every real pixel's features are the real image's.

Maps come back by the inverse shift, ``d = d' + M``; columns with no
disparity in the range (M > 0: the left image's first M) copy the nearest
column, as the margin does; their labels say occlusion and their confidence
is 0.  With M = 0 none of this runs (the method is unchanged, bit for bit).

The automatic range (:func:`choose_range`) runs the census stereo method at
1/:data:`AUTO_SCALE` resolution over a wide window of both signs and takes
the disparities of the pixels that pass the left-right check, trimmed by
:data:`AUTO_TRIM` on each side.  Structures a few pixels wide vanish at that
size (near branches, poles), and near is the side they lose, so a check at
1/:data:`AUTO_CHECK_SCALE` size searches those extremes widened by
:data:`AUTO_CHECK_MARGIN` plus that window's width again above them; the
extremes of both passes, widened by :data:`AUTO_MARGIN` below and
:data:`AUTO_MARGIN_NEAR` above, are the range.
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np

from .errors import InputError, InputWarning

#: Cost of a cell whose left or right pixel is padding: the largest value of
#: every matching cost (census, paper, acrt: [0, 1]; fst: -cos in [-1, 1]).
CEILING = 1.0
#: Intensity of the padding in the images the cross arms and SGM compare.
SENTINEL = np.float32(1.0e6)
#: The automatic range's coarse pass: 1/AUTO_SCALE of the image size.
AUTO_SCALE = 4
#: Coarse window, as fractions of the image width: -W/4 .. W/2.
AUTO_WINDOW = (0.25, 0.5)
#: Fraction of the coarse pass's consistent pixels left out at each end.
AUTO_TRIM = 0.0005
#: Margin added below the range found (the far side): max(AUTO_MARGIN[0] px,
#: AUTO_MARGIN[1] x the span); above it (the near side) AUTO_MARGIN_NEAR.
AUTO_MARGIN = (8, 0.2)
AUTO_MARGIN_NEAR = (16, 0.2)
#: The check: a second pass at 1/AUTO_CHECK_SCALE size (when the first ran at
#: 1/4 or smaller) over the first pass's extremes widened by
#: max(AUTO_CHECK_MARGIN[0] px, AUTO_CHECK_MARGIN[1] x the span) on each side,
#: with that window's width again added above it (nearer): where thin near
#: structures lost at 1/4 size lie.
AUTO_CHECK_SCALE = 2
AUTO_CHECK_MARGIN = (16, 0.2)
AUTO_CHECK_WIDEN = 1


def check_min_disparity(value) -> int:
    """M as an int (any sign; not a bool)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputError(f"min_disparity must be an integer, not {value!r}")
    return int(value)


def levels_of(disparity_range) -> tuple:
    """``(lo, hi)`` (inclusive, integers, lo < hi) -> ``(M, D)``."""
    try:
        lo, hi = disparity_range
    except (TypeError, ValueError):
        raise InputError(f"disparity_range must be (min, max), not {disparity_range!r}") from None
    lo, hi = check_min_disparity(lo), check_min_disparity(hi)
    if lo >= hi:
        raise InputError(f"disparity range {lo}..{hi}: the minimum must be smaller than the maximum")
    return lo, hi - lo + 1


def parse_range(text: str):
    """``--disp-range``: "auto" or "MIN:MAX" (inclusive) -> "auto" or (lo, hi)."""
    t = str(text).strip()
    if t.lower() == "auto":
        return "auto"
    lo, sep, hi = t.partition(":")
    try:
        if not sep:
            raise ValueError
        rng = int(lo), int(hi)
    except ValueError:
        raise InputError(f"--disp-range expects 'auto' or MIN:MAX (integers, e.g. -32:95), got {text!r}") from None
    levels_of(rng)
    return rng


def check_range(min_disparity: int, levels: int, width: int, patch: int) -> None:
    """InputError unless disparities M .. M+D-1 leave some pixel of an image
    ``width`` wide (cropped by the cost's patch) a right pixel inside the image."""
    M, D = int(min_disparity), int(levels)
    wc = int(width) - int(patch) + 1  # the cost volume's domain
    if M >= wc or M + D - 1 <= -wc:
        raise InputError(f"disparities {M}..{M + D - 1} leave no pixel a match: the right image's pixel "
                         f"x - d lies outside the image for every pixel ({wc} columns after the "
                         f"{patch}x{patch} patch's margin); use a range within -{wc - 1}..{wc - 1}")


class RangeFrame:
    """The working frame of one call with min disparity M != 0 (module docstring).

    ``shape``: the real image's (H_img, W_img); ``margin``: the cost's m.
    ``width``: the working image width W_img - M; ``p = -M``; ``W``: the
    real cropped width; ``Ww`` the working one."""

    def __init__(self, min_disparity: int, levels: int, shape, margin: int):
        self.M, self.D, self.m = int(min_disparity), int(levels), int(margin)
        self.p = -self.M
        Hi, Wi = int(shape[0]), int(shape[1])
        self.H, self.W = Hi - 2 * self.m, Wi - 2 * self.m
        self.Ww = self.W - self.M
        self.width = Wi - self.M
        self.masked = self.p > 0  # padding exists (M < 0): range.cl marks its cells

    def images(self, I_L, I_R):
        """The working-frame images the cost sees (padding: edge copies; their
        cells are masked, and the networks standardise with :meth:`stats`)."""
        p = self.p
        if p > 0:
            return (np.pad(I_L, ((0, 0), (p, 0)), mode="edge"), np.pad(I_R, ((0, 0), (0, p)), mode="edge"))
        return np.ascontiguousarray(I_L[:, -p:]), np.ascontiguousarray(I_R[:, :I_R.shape[1] + p])

    @staticmethod
    def stats(I_L, I_R):
        """The real images' (mean, std), for the networks' standardisation."""
        from .imageops import image_stats

        return image_stats(I_L), image_stats(I_R)

    def thresholds(self, S_L, S_R):
        """J_L, J_R: the images cross arms and SGM compare, on the working
        cropped domain (H x Ww), :data:`SENTINEL` where the pixel is not real."""
        m, H, W, Ww, p = self.m, self.H, self.W, self.Ww, self.p
        if p > 0:
            J_L = np.full((H, Ww), SENTINEL, np.float32)
            J_R = np.full((H, Ww), SENTINEL, np.float32)
            J_L[:, p:] = S_L[m:m + H, m:m + W]
            J_R[:, :W] = S_R[m:m + H, m:m + W]
            return J_L, J_R
        M = self.M
        return (np.ascontiguousarray(S_L[m:m + H, m + M:m + W], dtype=np.float32),
                np.ascontiguousarray(S_R[m:m + H, m:m + W - M], dtype=np.float32))

    # -- back to the real frame --------------------------------------------
    def _place(self, a, start_real, start_work, n, fill):
        out = np.empty(a.shape[:-1] + (self.W,), a.dtype)
        out[..., start_real:start_real + n] = a[..., start_work:start_work + n]
        if n < self.W:
            if fill == "edge":
                if start_real > 0:
                    out[..., :start_real] = out[..., start_real:start_real + 1]
                if start_real + n < self.W:
                    out[..., start_real + n:] = out[..., start_real + n - 1:start_real + n]
            else:
                out[..., :start_real] = fill
                out[..., start_real + n:] = fill
        return out

    def left(self, a, fill="edge"):
        """A left-frame map or volume ``[..., Ww]`` -> ``[..., W]`` (x = x' - p)."""
        if self.p >= 0:
            return self._place(a, 0, self.p, self.W, fill)
        return self._place(a, self.M, 0, self.W - self.M, fill)

    def right(self, a, fill="edge"):
        """A right-frame map ``[..., Ww]`` -> ``[..., W]`` (u = u')."""
        return self._place(a, 0, 0, min(self.W, self.Ww), fill)

    def valid(self):
        """Cells of the real range with a real right pixel: ``[D][1][W]`` bools."""
        d = self.M + np.arange(self.D)[:, None, None]
        x = np.arange(self.W)[None, None, :]
        return (x - d >= 0) & (x - d < self.W)

    def disparity(self, a):
        """D_SE (working, float32) -> the real frame, in real disparities."""
        return self.left(a + np.float32(self.M), "edge").astype(np.float32)

    def arrays(self, arrays: dict) -> None:
        """The kept intermediates (:class:`StereoResult`) moved to the real frame, in place."""
        M = self.M
        for name, a in list(arrays.items()):
            if name in ("C_CNN", "C_CBCA", "C_SGM", "C", "C_R"):  # C_R: mirrored, same shift
                v = self.left(a, np.nan)
                v[~np.broadcast_to(self.valid(), v.shape)] = np.nan
                arrays[name] = v
            elif name in ("D_L", "D_INT", "D_SE"):
                arrays[name] = self.left(a + a.dtype.type(M), "edge")
            elif name == "D_R":
                arrays[name] = self.right(a + a.dtype.type(M), "edge")
            elif name == "labels":
                arrays[name] = self.left(a, 2)  # no disparity in the range: occlusion
            elif name == "confidence":
                arrays[name] = self.left(a, 0.0)


def mask_reference(vol, lo: int, hi: int, ceiling: float = CEILING):
    """Numpy twin of ``range_mask`` (kernels/range.cl) on a [D][H][W] volume (a copy)."""
    out = np.array(vol, copy=True)
    D, _, W = out.shape
    d = np.arange(D)[:, None]
    x = np.arange(W)[None, :]
    sel = (x - d >= 0) & ((x < lo) | (x - d >= hi))
    out[np.broadcast_to(sel[:, None, :], out.shape)] = ceiling
    return out


class RangeMask:
    """``kernels/range.cl``: :data:`CEILING` into the padding's cells, in place."""

    def __init__(self, ctx, half: bool = False):
        self.ctx = ctx
        self.kern = ctx.kernel("range.cl", "range_mask", VOL_HALF=int(half))

    def __call__(self, d_cost, D, H, W, lo, hi, ceiling=CEILING):
        from .opencl.context import launch

        i32 = np.int32
        launch(self.ctx, "range mask", self.kern, (W, H, D), d_cost, i32(D), i32(H), i32(W), i32(lo), i32(hi),
               np.float32(ceiling))
        return d_cost


def coarse_scale(shape) -> int:
    """1/AUTO_SCALE, or less reduction for small images (>= 64 columns, 32 rows at the coarse size)."""
    s = AUTO_SCALE
    while s > 1 and (shape[1] // s < 64 or shape[0] // s < 32):
        s //= 2
    return s


def _coarse_pass(matcher, I_L, I_R, s, window):
    """The census stereo method at 1/s size over ``window`` (coarse px): the
    extremes (full-size px) of the disparities of the pixels that pass the
    left-right check, trimmed by :data:`AUTO_TRIM` at each end (None when
    fewer than 16 pass), and the fraction of such pixels."""
    import cv2

    Hi, Wi = I_L.shape
    if s > 1:
        size = (Wi // s, Hi // s)
        L = cv2.resize(I_L, size, interpolation=cv2.INTER_AREA)
        R = cv2.resize(I_R, size, interpolation=cv2.INTER_AREA)
    else:
        L, R = I_L, I_R
    coarse = matcher._coarse_matcher()
    matcher._room_for_pass(coarse, L.shape, window)  # what the matcher kept stays only if the pass fits beside it
    with warnings.catch_warnings():  # a pass over a window that leaves most pixels out looks "swapped":
        warnings.simplefilter("ignore", InputWarning)  # the full-size match says what applies
        res = coarse.compute(L, R, confidence=True, disparity_range=window)
    m = coarse.margin
    d = res.disparity[m:-m, m:-m]
    ok = (res.labels[m:-m, m:-m] == 0) & np.isfinite(d)
    used = float(ok.mean()) if ok.size else 0.0
    if ok.sum() < 16:  # too few to trust
        return None, used
    found = np.quantile(np.float32(s) * d[ok], [AUTO_TRIM, 1.0 - AUTO_TRIM])
    return (float(found[0]), float(found[1])), used


def _with_margin(lo, hi, below, above):
    """``(lo, hi)`` widened by max(px, frac x the span) below and above (``(px, frac)`` each)."""
    return (math.floor(lo - max(below[0], below[1] * (hi - lo))),
            math.ceil(hi + max(above[0], above[1] * (hi - lo))))


def choose_range(matcher, I_L, I_R) -> dict:
    """The automatic range of one pair (gray float32 [0, 1] images).

    Returns ``{"range": (lo, hi), "found": the trimmed extremes before the
    margin (full-size px, both passes), "scale", "window": the first pass's
    window (full-size px), "consistent": fraction of its pixels used,
    "check": the check's window (full-size px; None when the first pass ran
    at 1/2 size or finer), "check_scale", "found_first", "found_check": each
    pass's extremes, "seconds"}``."""
    t0 = time.perf_counter()
    Hi, Wi = I_L.shape
    s = coarse_scale(I_L.shape)
    wc = Wi // s
    lo_c, hi_c = -int(wc * AUTO_WINDOW[0]), int(wc * AUTO_WINDOW[1])
    extremes, used = _coarse_pass(matcher, I_L, I_R, s, (lo_c, hi_c))
    # nothing consistent: the whole coarse window
    found = extremes if extremes is not None else (float(lo_c * s), float(hi_c * s))
    first, check, found_check = found, None, None
    if s >= 2 * AUTO_CHECK_SCALE and extremes is not None:
        # the check: 1/AUTO_CHECK_SCALE size over the first extremes with AUTO_CHECK_MARGIN,
        # plus AUTO_CHECK_WIDEN x that width above (within the first pass's window)
        s2 = AUTO_CHECK_SCALE
        c_lo, c_hi = _with_margin(*found, AUTO_CHECK_MARGIN, AUTO_CHECK_MARGIN)
        w_lo = max(c_lo, lo_c * s) // s2
        w_hi = -(-min(c_hi + AUTO_CHECK_WIDEN * (c_hi - c_lo), hi_c * s) // s2)
        check = (int(w_lo * s2), int(w_hi * s2))
        found_check, _ = _coarse_pass(matcher, I_L, I_R, s2, (int(w_lo), int(w_hi)))
        if found_check is not None:
            found = (min(found[0], found_check[0]), max(found[1], found_check[1]))
    lo, hi = _with_margin(*found, AUTO_MARGIN, AUTO_MARGIN_NEAR)
    if found[0] >= 0:  # no negative disparity found: the margin stops at 0 (a parallel rig's are >= 0)
        lo = max(lo, 0)
    # within what the image allows: fewer levels than the width, some pixel with a match
    wcrop = Wi - 2 * matcher.margin
    lo = max(lo, -(wcrop - 1))
    hi = min(hi, wcrop - 1, lo + Wi - 2)
    if hi <= lo:
        hi = lo + 1
    return {"range": (int(lo), int(hi)), "found": found, "scale": s, "window": (lo_c * s, hi_c * s),
            "consistent": used, "check": check, "check_scale": AUTO_CHECK_SCALE if check else None,
            "found_first": first, "found_check": found_check,
            "seconds": time.perf_counter() - t0}
