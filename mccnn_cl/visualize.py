"""Colour pictures of disparity maps, with a legend bar, and error maps.

Everything returns 8-bit BGR images (cv2's order) ready for
:func:`mccnn_cl.io.write_image`.  Colour maps are cv2's (default TURBO: near =
large disparity = red, far = blue); invalid pixels are black.
"""

from __future__ import annotations

import cv2
import numpy as np

from .errors import InputError

__all__ = ["disparity_range", "colorize", "legend_bar", "colorize_with_legend", "error_image",
           "label", "COLORMAPS"]

COLORMAPS = {
    "turbo": cv2.COLORMAP_TURBO,
    "jet": cv2.COLORMAP_JET,
    "magma": cv2.COLORMAP_MAGMA,
    "viridis": cv2.COLORMAP_VIRIDIS,
    "inferno": cv2.COLORMAP_INFERNO,
    "gray": None,
}


def _cmap(name):
    if name not in COLORMAPS:
        raise InputError(f"unknown colour map {name!r}; choose one of {', '.join(COLORMAPS)}")
    return COLORMAPS[name]


def disparity_range(*maps) -> tuple:
    """(min(0, smallest), largest) over the finite values of the given maps — a
    common scale for comparisons: from 0 for the usual non-negative maps, from
    the smallest disparity when some are negative (a range with a negative
    minimum disparity); (0, 1) when no value is finite, ``vmin + 1`` as the top
    when every value is the same."""
    lo, hi = 0.0, None
    for m in maps:
        if m is None:
            continue
        m = np.asarray(m, dtype=np.float64)
        fin = m[np.isfinite(m)]
        if fin.size:
            lo = min(lo, float(fin.min()))
            hi = float(fin.max()) if hi is None else max(hi, float(fin.max()))
    if hi is None or hi <= lo:
        hi = lo + 1.0
    return lo, hi


def colorize(disp, vmin=None, vmax=None, colormap="turbo", invalid=(0, 0, 0)) -> np.ndarray:
    """Map ``disp`` linearly from [vmin, vmax] onto a cv2 colour map; non-finite pixels get ``invalid``.
    Defaults: :func:`disparity_range` of ``disp`` (vmin = min(0, its smallest finite value))."""
    d = np.asarray(disp, dtype=np.float64)
    if d.ndim != 2:
        raise InputError(f"colorize: expected an (H, W) disparity map, got shape {d.shape}")
    lo, hi = disparity_range(d)
    vmin = lo if vmin is None else float(vmin)
    vmax = hi if vmax is None else float(vmax)
    if vmax <= vmin:
        vmax = vmin + 1.0
    fin = np.isfinite(d)
    scaled = np.zeros(d.shape, np.uint8)
    scaled[fin] = np.clip(np.round((d[fin] - vmin) / (vmax - vmin) * 255.0), 0, 255).astype(np.uint8)
    cm = _cmap(colormap)
    img = cv2.cvtColor(scaled, cv2.COLOR_GRAY2BGR) if cm is None else cv2.applyColorMap(scaled, cm)
    img[~fin] = invalid
    return img


def _nice_step(span, max_ticks):
    raw = span / max(max_ticks, 1)
    mag = 10 ** np.floor(np.log10(raw)) if raw > 0 else 1.0
    for m in (1, 2, 2.5, 5, 10):
        if m * mag >= raw:
            return m * mag
    return 10 * mag


def legend_bar(width, vmin, vmax, colormap="turbo", height=34, title="disparity [px]",
               scale=0.35) -> np.ndarray:
    """A ``width``-wide strip: the colour ramp from vmin (left) to vmax (right) with tick labels."""
    width = int(width)
    if width < 16:
        raise InputError("legend_bar: width must be at least 16 px")
    vmin, vmax = float(vmin), float(vmax)
    if vmax <= vmin:
        vmax = vmin + 1.0
    font, thick, pad = cv2.FONT_HERSHEY_SIMPLEX, 1, 4
    (tw, th), _ = cv2.getTextSize("000", font, scale, thick)
    bar_h = max(8, height // 3)
    # rows: colour bar, tick labels, then the title (centred) on a line of its own
    height = max(int(height), bar_h + 2 * th + 3 * pad + 4 if title else bar_h + th + 2 * pad)
    strip = np.full((height, width, 3), 255, np.uint8)
    ramp = np.linspace(vmin, vmax, width)[None, :].repeat(bar_h, 0)
    strip[0:bar_h, :] = colorize(ramp, vmin, vmax, colormap)
    step = _nice_step(vmax - vmin, max(2, width // (tw + 24)))
    first = np.ceil(vmin / step) * step
    for v in np.arange(first, vmax + 1e-9, step):
        x = int(round((v - vmin) / (vmax - vmin) * (width - 1)))
        cv2.line(strip, (x, 0), (x, bar_h + 2), (0, 0, 0), 1)
        text = f"{v:g}"
        (w, _), _ = cv2.getTextSize(text, font, scale, thick)
        tx = int(np.clip(x - w // 2, 0, width - w))
        cv2.putText(strip, text, (tx, bar_h + pad + th), font, scale, (0, 0, 0), thick, cv2.LINE_AA)
    if title:
        (w, _), _ = cv2.getTextSize(title, font, scale, thick)
        y = bar_h + 2 * pad + 2 * th + 2
        cv2.putText(strip, title, (max((width - w) // 2, 0), y), font, scale, (80, 80, 80), thick,
                    cv2.LINE_AA)
    return strip


def colorize_with_legend(disp, vmin=None, vmax=None, colormap="turbo") -> np.ndarray:
    """:func:`colorize` with a :func:`legend_bar` stacked underneath (same scale;
    defaults as :func:`colorize`'s)."""
    d = np.asarray(disp, dtype=np.float64)
    lo, hi = disparity_range(d)
    vmin = lo if vmin is None else vmin
    vmax = hi if vmax is None else vmax
    img = colorize(d, vmin, vmax, colormap)
    bar = legend_bar(max(img.shape[1], 160), vmin, vmax, colormap)
    if bar.shape[1] > img.shape[1]:  # narrow image: centre it on a white canvas
        canvas = np.full((img.shape[0], bar.shape[1], 3), 255, np.uint8)
        x0 = (bar.shape[1] - img.shape[1]) // 2
        canvas[:, x0:x0 + img.shape[1]] = img
        img = canvas
    return np.vstack([img, bar])


def error_image(pred, gt, threshold=3.0, mask=None) -> np.ndarray:
    """Error map: black = no GT, green = within ``threshold``, red = worse (brighter with the error),
    magenta = no prediction where GT exists."""
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise InputError(f"error_image: prediction {pred.shape} and GT {gt.shape} differ in size")
    ev = np.isfinite(gt)
    if mask is not None:
        ev &= np.asarray(mask, dtype=bool)
    img = np.zeros(gt.shape + (3,), np.uint8)
    fin = np.isfinite(pred)
    with np.errstate(invalid="ignore"):
        err = np.abs(pred - gt)
    good = ev & fin & (err <= threshold)
    bad = ev & fin & (err > threshold)
    img[good] = (0, 170, 0)
    level = np.clip(err / (4 * threshold), 0.0, 1.0)
    img[bad, 2] = (128 + 127 * level[bad]).astype(np.uint8)
    img[ev & ~fin] = (255, 0, 255)
    return img


def label(img, text, height=18, scale=0.4) -> np.ndarray:
    """``img`` with a white caption strip on top."""
    strip = np.full((height, img.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, text, (3, height - 6), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([strip, img])
