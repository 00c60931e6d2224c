"""Numpy twins of the disparity stages (the executable specification).

Written for clarity, loops and all; the OpenCL kernels in ``kernels/
disparity.cl``, ``interpolate.cl``, ``subpixel.cl``, ``refine.cl`` and
``census.cl`` are tested against these functions element by element.

Conventions (see ``kernels/common.h``): cost volumes are float32
``C[d, y, x]`` on the cropped domain, cell (d, y, x) compares left (x, y)
with right (x - d, y) and is invalid when x - d < 0 (validity is decided by
index, never by value).  Disparity maps are int32 (WTA, labels, D_INT) or
float32 (D_SE and after).
"""

from __future__ import annotations

import numpy as np

from ..conventions import CORRECT, DIRECTIONS, MISMATCH, OCCLUSION  # noqa: F401 (the stages' too)


# -- winner-take-all -------------------------------------------------------
def wta_left(C: np.ndarray) -> np.ndarray:
    """D^L(x, y) = argmin over valid d (d <= x) of C[d, y, x]; ties -> smallest d."""
    D, H, W = C.shape
    out = np.zeros((H, W), np.int32)
    for y in range(H):
        for x in range(W):
            best_d, best = 0, C[0, y, x]
            for d in range(1, min(D - 1, x) + 1):
                if C[d, y, x] < best:
                    best_d, best = d, C[d, y, x]
            out[y, x] = best_d
    return out


def right_cost_volume(C: np.ndarray) -> np.ndarray:
    """C_R[d, y, x] = C_L[d, y, x + d]; NaN where x + d >= W (derived, not recomputed)."""
    D, H, W = C.shape
    CR = np.full_like(C, np.nan)
    for d in range(D):
        if d < W:
            CR[d, :, :W - d] = C[d, :, d:]
    return CR


def wta_right(C: np.ndarray) -> np.ndarray:
    """D^R(x, y) = argmin over valid d (x + d < W) of C_L[d, y, x + d]; ties -> smallest d."""
    D, H, W = C.shape
    out = np.zeros((H, W), np.int32)
    for y in range(H):
        for x in range(W):
            best_d, best = 0, C[0, y, x]
            for d in range(1, min(D - 1, W - 1 - x) + 1):
                if C[d, y, x + d] < best:
                    best_d, best = d, C[d, y, x + d]
            out[y, x] = best_d
    return out


# -- left-right check and interpolation ----------------------------------
def lr_check(DL: np.ndarray, DR: np.ndarray, D: int, threshold: float = 1.0,
             right_width: int | None = None) -> np.ndarray:
    """Labels: CORRECT if |d - D^R(x-d)| <= threshold for d = D^L(p); MISMATCH if
    that holds for another d' in [0, D) with 0 <= x - d' < right_width; OCCLUSION
    otherwise.  ``right_width``: columns of the real right image (None: W, the
    real pair; in the working frame of a range with M < 0 the real width, so
    that the right image's padding columns are never a candidate's pd')."""
    H, W = DL.shape
    Wr = W if right_width is None else int(right_width)
    labels = np.full((H, W), OCCLUSION, np.int32)
    for y in range(H):
        for x in range(W):
            d = int(DL[y, x])
            if 0 <= x - d < Wr and d >= 0 and abs(d - int(DR[y, x - d])) <= threshold:
                labels[y, x] = CORRECT
                continue
            for e in range(max(0, x - Wr + 1), min(D - 1, x) + 1):
                if e != d and abs(e - int(DR[y, x - e])) <= threshold:
                    labels[y, x] = MISMATCH
                    break
    return labels


def _round_half_away(v: float) -> int:
    return int(np.sign(v) * np.floor(abs(v) + 0.5))


def interpolate(DL: np.ndarray, labels: np.ndarray, directions="paper",
                stop_at_any: bool = False, first_column: int = 0) -> np.ndarray:
    """D_INT from D^L and the labels (both read, never updated while filling).

    occlusion: first CORRECT pixel moving left, else moving right, else keep.
    mismatch: along each of the 16 directions the first pixel that is CORRECT
    (or, ``stop_at_any``, not MISMATCH) gives one value; the result is the
    upper median ``sorted(vals)[n // 2]``; no value -> keep.
    ``first_column``: columns before it are not part of the image (the working
    frame's padding of a range with M < 0): searches and walks end there as at
    the map's edge; on the columns from it on, D_INT is the one of the maps
    without those columns.
    """
    dirs = DIRECTIONS[directions] if isinstance(directions, str) else np.asarray(directions, np.float32)
    H, W = DL.shape
    lo = int(first_column)
    out = DL.astype(np.int32).copy()
    for y in range(H):
        for x in range(W):
            if labels[y, x] == OCCLUSION:
                left = [xx for xx in range(x - 1, lo - 1, -1) if labels[y, xx] == CORRECT]
                right = [xx for xx in range(max(x, lo - 1) + 1, W) if labels[y, xx] == CORRECT]
                if left:
                    out[y, x] = DL[y, left[0]]
                elif right:
                    out[y, x] = DL[y, right[0]]
            elif labels[y, x] == MISMATCH:
                vals = []
                for dx, dy in dirs:
                    s = 1
                    while True:
                        qx = lo + _round_half_away(np.float32(x - lo) + np.float32(s) * dx)  # real columns
                        qy = _round_half_away(np.float32(y) + np.float32(s) * dy)
                        if not (lo <= qx < W and 0 <= qy < H):
                            break
                        lq = labels[qy, qx]
                        if lq == CORRECT or (stop_at_any and lq != MISMATCH):
                            vals.append(int(DL[qy, qx]))
                            break
                        s += 1
                if vals:
                    out[y, x] = sorted(vals)[len(vals) // 2]
    return out


# -- subpixel enhancement --------------------------------------------------
def subpixel(C: np.ndarray, DINT: np.ndarray, min_denominator: float = 0.0,
             clamp_step: bool = True, right_width: int | None = None) -> np.ndarray:
    """D_SE = d - (C+ - C-) / (2 (C+ - 2C + C-)) where 1 <= d <= D-2, d+1 <= x,
    x - (d-1) < right_width (the three cells' right pixels inside the real right
    image; None: W, the real pair, where it always holds) and the denominator >
    min_denominator; otherwise d.  ``clamp_step`` (the default, as the stage's and
    the matcher's): the step clamped to [-1, 1].  float32 arithmetic."""
    D, H, W = C.shape
    Wr = W if right_width is None else int(right_width)
    out = DINT.astype(np.float32)
    two = np.float32(2.0)
    for y in range(H):
        for x in range(W):
            d = int(DINT[y, x])
            if 1 <= d and d + 1 <= D - 1 and d + 1 <= x and x - (d - 1) < Wr:
                cm, c0, cp = C[d - 1, y, x], C[d, y, x], C[d + 1, y, x]
                denom = cp - two * c0 + cm
                if denom > np.float32(min_denominator):
                    step = (cp - cm) / (two * denom)
                    if clamp_step:
                        step = np.float32(min(max(step, -1.0), 1.0))
                    out[y, x] = np.float32(d) - step
    return out


# -- refinement ----------------------------------------------------------------
def enlarge(D: np.ndarray, margin: int, shape) -> np.ndarray:
    """Place the cropped map at (margin, margin) of an image of ``shape``, copying
    the border disparities outwards."""
    Ho, Wo = shape
    H, W = D.shape
    out = np.empty((Ho, Wo), D.dtype)
    for y in range(Ho):
        for x in range(Wo):
            out[y, x] = D[min(max(y - margin, 0), H - 1), min(max(x - margin, 0), W - 1)]
    return out


def median_filter(D: np.ndarray, size: int = 5) -> np.ndarray:
    """size x size median, pixels outside replaced by the nearest border pixel."""
    r = size // 2
    padded = np.pad(D, r, mode="edge")
    H, W = D.shape
    out = np.empty_like(D)
    for y in range(H):
        for x in range(W):
            out[y, x] = np.sort(padded[y:y + size, x:x + size], axis=None)[size * size // 2]
    return out


def bilateral(D: np.ndarray, guide: np.ndarray, sigma: float, radius: int, tau: float) -> np.ndarray:
    """D_BF(p) = sum_q D(q) g(|p-q|) 1{|G(p) - G(q)| < tau} / W(p) over the
    (2 radius + 1)^2 window clipped to the map; g unnormalised Gaussian of
    ``sigma``.  ``guide`` is I^L (paper) or D itself (released code).  The
    indicator is evaluated in float32, like the kernel."""
    H, W = D.shape
    tau = np.float32(tau)
    out = np.empty((H, W), np.float32)
    for y in range(H):
        for x in range(W):
            y0, y1 = max(y - radius, 0), min(y + radius, H - 1)
            x0, x1 = max(x - radius, 0), min(x + radius, W - 1)
            yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
            g = np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2.0 * sigma ** 2))
            ok = np.abs(guide[y0:y1 + 1, x0:x1 + 1] - guide[y, x]) < tau
            w = g * ok
            out[y, x] = (w * D[y0:y1 + 1, x0:x1 + 1]).sum() / w.sum() if w.sum() > 0 else D[y, x]
    return out


# -- census cost -----------------------------------------------------------------
CENSUS_RADIUS = 4


def census_transform(img: np.ndarray) -> np.ndarray:
    """80 bits per pixel of the cropped domain (margin 4), as an (H, W, 80) bool
    array in the kernel's bit order: neighbours row-major over dy, dx = -4..4,
    centre skipped; bit set when the neighbour is darker than the centre."""
    r = CENSUS_RADIUS
    Hi, Wi = img.shape
    H, W = Hi - 2 * r, Wi - 2 * r
    bits = np.zeros((H, W, 80), bool)
    for y in range(H):
        for x in range(W):
            c = img[y + r, x + r]
            k = 0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    if dx == 0 and dy == 0:
                        continue
                    bits[y, x, k] = img[y + r + dy, x + r + dx] < c
                    k += 1
    return bits


def census_cost(left: np.ndarray, right: np.ndarray, D: int, min_disparity: int = 0) -> np.ndarray:
    """C[k, y, x] = Hamming(census_L(x, y), census_R(x - d, y)) / 80 at d = min_disparity + k;
    NaN unless 0 <= x - d < W."""
    bl, br = census_transform(left), census_transform(right)
    H, W, _ = bl.shape
    C = np.full((D, H, W), np.nan, np.float32)
    for k in range(D):
        d = min_disparity + k
        for x in range(max(d, 0), min(W, W + d)):
            C[k, :, x] = (bl[:, x] != br[:, x - d]).sum(axis=1).astype(np.float32) / np.float32(80)
    return C
