"""Disparity error metrics of the KITTI and Middlebury benchmarks.

Conventions (shared by every function here):

* ``pred`` is an (H, W) disparity map in pixels; a non-finite value (NaN,
  ±inf) is a pixel the method left *invalid*.
* ``gt`` is the ground truth on the same grid; a non-finite value is
  *unknown* (the loaders in :mod:`mccnn_cl.evaluation.datasets` put NaN there; KITTI's 0
  and Middlebury's +inf are both turned into "unknown" by them).
* ``mask`` (optional, bool) restricts the evaluation further, e.g. to the
  non-occluded pixels (KITTI ``disp_noc``, Middlebury ``mask0nocc``).
* The evaluated set is ``isfinite(gt) & mask``.  A pixel of that set where
  ``pred`` is invalid counts as an **error** in every error rate (the
  benchmarks' "dense" evaluation would interpolate it first; counting it as
  bad is the stricter choice and keeps sparse methods honest).  The end-point
  error is averaged over the evaluated pixels that *have* a prediction, and
  :func:`density` reports how many have one.
* Rates are returned in **percent**.  With no evaluated pixel a rate is NaN.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

__all__ = ["evaluated", "bad_pixel_rate", "kitti_3px", "kitti_d1", "middlebury_bad",
           "end_point_error", "density", "evaluate_disparity", "bad_pixel_map", "fill_invalid",
           "METRIC_NAMES", "sparsification", "SPARSIFICATION_FRACTIONS"]

#: Short names and descriptions of the keys returned by :func:`evaluate_disparity`.
METRIC_NAMES = {
    "bad3_noc": "KITTI 3-px error on non-occluded GT (|d - gt| > 3), %",
    "bad3_all": "KITTI 3-px error on all GT, %",
    "d1_all": "KITTI 2015 D1 on all GT (|d - gt| > 3 and > 5 % of gt), %",
    "bad2_noc": "Middlebury bad-2.0 on non-occluded GT (|d - gt| > 2), %",
    "bad2_all": "Middlebury bad-2.0 on all GT, %",
    "epe_all": "end-point error: mean |d - gt| over all GT pixels with a prediction, px",
    "density": "pixels of the image with a (finite) prediction, %",
}


def _check(pred, gt, mask):
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape or pred.ndim != 2:
        raise InputError(f"prediction {pred.shape} and ground truth {gt.shape} must be (H, W) "
                         "maps of the same size")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != gt.shape:
            raise InputError(f"mask {mask.shape} does not match the ground truth {gt.shape}")
    return pred, gt, mask


def evaluated(gt, mask=None) -> np.ndarray:
    """Boolean map of the evaluated pixels: known GT (finite) and inside ``mask``."""
    ok = np.isfinite(np.asarray(gt, dtype=np.float64))
    if mask is not None:
        ok &= np.asarray(mask, dtype=bool)
    return ok


def _bad_map(pred, gt, threshold, relative=None):
    """Bad pixels among all pixels (invalid prediction = bad); callers intersect with the GT set."""
    with np.errstate(invalid="ignore"):
        err = np.abs(pred - gt)
        bad = ~np.isfinite(pred) | (err > threshold)
        if relative is not None:
            bad = ~np.isfinite(pred) | ((err > threshold) & (err > relative * np.abs(gt)))
    return bad


def bad_pixel_rate(pred, gt, threshold, mask=None, relative=None) -> float:
    """Percentage of evaluated pixels with ``|pred - gt| > threshold``.

    With ``relative`` (e.g. 0.05) a pixel is bad only if the error also exceeds
    ``relative * gt`` (KITTI 2015's D1 rule).  Invalid predictions are bad.
    """
    pred, gt, mask = _check(pred, gt, mask)
    ev = evaluated(gt, mask)
    n = int(ev.sum())
    if n == 0:
        return float("nan")
    bad = _bad_map(pred, gt, threshold, relative) & ev
    return 100.0 * float(bad.sum()) / n


def kitti_3px(pred, gt, mask=None) -> float:
    """KITTI 2012's error: % of evaluated pixels off by more than 3 px (the paper's measure)."""
    return bad_pixel_rate(pred, gt, 3.0, mask)


def kitti_d1(pred, gt, mask=None) -> float:
    """KITTI 2015's D1: % of evaluated pixels off by more than 3 px *and* more than 5 % of gt."""
    return bad_pixel_rate(pred, gt, 3.0, mask, relative=0.05)


def middlebury_bad(pred, gt, mask=None, threshold=2.0) -> float:
    """Middlebury's bad-T (default bad-2.0): % of evaluated pixels off by more than T px."""
    return bad_pixel_rate(pred, gt, threshold, mask)


def end_point_error(pred, gt, mask=None) -> float:
    """Mean ``|pred - gt|`` over evaluated pixels with a finite prediction (px); NaN if none."""
    pred, gt, mask = _check(pred, gt, mask)
    ev = evaluated(gt, mask) & np.isfinite(pred)
    if not ev.any():
        return float("nan")
    return float(np.mean(np.abs(pred[ev] - gt[ev])))


def density(pred, mask=None) -> float:
    """Percentage of pixels (inside ``mask`` if given, else the whole image) with a finite prediction."""
    pred = np.asarray(pred, dtype=np.float64)
    fin = np.isfinite(pred)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != pred.shape:
            raise InputError(f"mask {mask.shape} does not match the prediction {pred.shape}")
        n = int(mask.sum())
        return 100.0 * float((fin & mask).sum()) / n if n else float("nan")
    return 100.0 * float(fin.sum()) / fin.size if fin.size else float("nan")


def evaluate_disparity(pred, gt, valid_noc=None, valid_all=None) -> dict:
    """All metrics of :data:`METRIC_NAMES` for one map.

    ``valid_all`` restricts "all GT" (default: wherever ``gt`` is finite);
    ``valid_noc`` gives the non-occluded subset — when it is ``None`` (the
    dataset has no occlusion mask) the ``*_noc`` entries are NaN rather than a
    silent copy of the ``*_all`` ones.
    """
    pred, gt, valid_all = _check(pred, gt, valid_all)
    out = {
        "bad3_all": kitti_3px(pred, gt, valid_all),
        "d1_all": kitti_d1(pred, gt, valid_all),
        "bad2_all": middlebury_bad(pred, gt, valid_all),
        "epe_all": end_point_error(pred, gt, valid_all),
        "density": density(pred),
    }
    if valid_noc is not None:
        noc = np.asarray(valid_noc, dtype=bool)
        if valid_all is not None:
            noc = noc & valid_all
        out["bad3_noc"] = kitti_3px(pred, gt, noc)
        out["bad2_noc"] = middlebury_bad(pred, gt, noc)
    else:
        out["bad3_noc"] = out["bad2_noc"] = float("nan")
    return {k: out[k] for k in METRIC_NAMES}


def bad_pixel_map(pred, gt, threshold=3.0, mask=None, relative=None) -> np.ndarray:
    """int8 map: -1 not evaluated, 0 correct, 1 bad (error > threshold or no prediction)."""
    pred, gt, mask = _check(pred, gt, mask)
    ev = evaluated(gt, mask)
    out = np.full(gt.shape, -1, np.int8)
    out[ev] = _bad_map(pred, gt, threshold, relative)[ev].astype(np.int8)
    return out


def fill_invalid(disp) -> np.ndarray:
    """Fill invalid (non-finite) pixels the way the KITTI devkit does for sparse results.

    Along each row, a gap between two valid pixels takes the *smaller* of
    their disparities (the background); a gap at a row's end takes the nearest
    valid value.  Then, in each column, the rows above its first and below its
    last valid pixel (whole rows with no valid pixel) take that pixel's value;
    as in the devkit (``interpolateBackground``), an empty row *between* valid
    rows is not filled, and it and a map with no valid pixel at all are
    returned as zeros (counted wrong wherever the ground truth is above the
    threshold).
    """
    d = np.array(disp, dtype=np.float32, copy=True)
    if d.ndim != 2:
        raise InputError(f"fill_invalid: expected an (H, W) map, got shape {d.shape}")

    def fill_lines(a, interior=True):  # fill along axis 1, in place; rows without data untouched
        for row in a:
            ok = np.isfinite(row)
            if ok.all() or not ok.any():
                continue
            if not interior:  # only beyond the first and the last valid pixel
                first, last = np.flatnonzero(ok)[[0, -1]]
                row[:first] = row[first]
                row[last + 1:] = row[last]
                continue
            idx = np.arange(row.size)
            # nearest valid index to the left and to the right of every pixel
            left = np.maximum.accumulate(np.where(ok, idx, -1))
            right = np.minimum.accumulate(np.where(ok, idx, row.size)[::-1])[::-1]
            vals_l = np.where(left >= 0, row[np.clip(left, 0, None)], np.inf)
            vals_r = np.where(right < row.size, row[np.clip(right, None, row.size - 1)], np.inf)
            fill = np.minimum(vals_l, vals_r)
            row[~ok] = fill[~ok]
        return a

    fill_lines(d)
    if not np.isfinite(d).all():
        fill_lines(d.T, interior=False)
    d[~np.isfinite(d)] = 0.0
    return d


#: Fractions of the evaluated pixels dropped along a sparsification curve: 0 .. 90 % in 5 % steps.
SPARSIFICATION_FRACTIONS = tuple(round(0.05 * i, 2) for i in range(19))


def _kept_error(bad, key, fractions):
    """Error rate (%) of the pixels kept after dropping the fraction f with the
    lowest ``key``, for each f.  Pixels of equal key are dropped as a group in
    random order: a cut inside a group removes its errors pro rata (the
    expected value), so ties (e.g. every confidence-0 pixel) favour no pixel."""
    order = np.argsort(key, kind="stable")
    ks, bs = key[order], bad[order].astype(np.float64)
    n = len(ks)
    cum = np.concatenate([[0.0], np.cumsum(bs)])
    out = []
    for f in fractions:
        k = int(round(f * n))
        if k >= n:
            out.append(float("nan"))
            continue
        dropped = 0.0
        if k > 0:
            a, b = np.searchsorted(ks, ks[k - 1], "left"), np.searchsorted(ks, ks[k - 1], "right")
            dropped = cum[a] + (k - a) * (cum[b] - cum[a]) / (b - a)
        out.append(100.0 * (cum[n] - dropped) / (n - k))
    return np.array(out)


def sparsification(pred, gt, confidence, threshold, mask=None, fractions=SPARSIFICATION_FRACTIONS) -> dict:
    """Sparsification curve of a confidence map against its oracle.

    Over the evaluated pixels (:func:`evaluated`), ``curve[i]`` is the bad-T
    rate (%, ``|pred - gt| > threshold``, invalid predictions bad) of the
    pixels kept after dropping the ``fractions[i]`` of them with the lowest
    ``confidence``; ``oracle[i]`` the same when dropping by the true error
    (the best any confidence can do).  ``auc`` / ``oracle_auc``: the curves'
    mean over [fractions[0], fractions[-1]] (trapezoids), in %; the closer
    ``auc`` to ``oracle_auc``, the better the confidence ranks the errors
    (``curve[0]`` is the plain error rate; a random confidence keeps it flat).
    """
    pred, gt, mask = _check(pred, gt, mask)
    conf = np.asarray(confidence, dtype=np.float64)
    if conf.shape != gt.shape:
        raise InputError(f"confidence {conf.shape} does not match the ground truth {gt.shape}")
    fr = np.asarray(fractions, dtype=np.float64)
    if fr.ndim != 1 or len(fr) < 2 or np.any(np.diff(fr) <= 0) or fr[0] < 0 or fr[-1] >= 1:
        raise InputError("fractions must be at least two increasing values in [0, 1)")
    ev = evaluated(gt, mask)
    if not np.isfinite(conf[ev]).all():
        raise InputError("confidence must be finite on the evaluated pixels")
    if not ev.any():
        raise InputError("sparsification: no evaluated pixel (no ground truth inside the mask)")
    bad = _bad_map(pred, gt, threshold)[ev]
    with np.errstate(invalid="ignore"):
        err = np.where(np.isfinite(pred[ev]), np.abs(pred[ev] - gt[ev]), np.inf)
    curve, oracle = _kept_error(bad, conf[ev], fr), _kept_error(bad, -err, fr)
    span = fr[-1] - fr[0]
    return {"fractions": fr, "curve": curve, "oracle": oracle,
            "auc": float(np.trapezoid(curve, fr) / span), "oracle_auc": float(np.trapezoid(oracle, fr) / span)}
