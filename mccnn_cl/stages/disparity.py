"""Computing the disparity image (paper, "Computing the disparity image",
"Interpolation", "Subpixel enhancement").

Stages (device buffers in and out; each ``__call__`` only enqueues work):

* :class:`WinnerTakeAll` - ``kernels/disparity.cl``: D^L and D^R (int32), both
  from the SAME left-reference volume (C_R(d, y, x) = C_L(d, y, x + d)).
* :class:`RightReference` - ``kernels/disparity.cl``: the mirrored
  right-reference volume, to run the stereo method with the right image as
  the reference (``right_reference="aggregated"`` in the pipeline).
* :class:`LeftRightCheck` - ``kernels/disparity.cl``: labels correct /
  mismatch / occlusion (int32 0 / 1 / 2).
* :class:`Interpolate` - ``kernels/interpolate.cl``: D_INT (int32).
* :class:`Subpixel` - ``kernels/subpixel.cl``: D_SE (float32).

Every ``__call__`` accepts ``out=`` (a buffer to write into, e.g. poisoned by
a test); otherwise it allocates one.  The numpy twins are in
:mod:`mccnn_cl.reference.disparity`.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..opencl.context import launch
from ..conventions import CORRECT, DIRECTIONS, MISMATCH, OCCLUSION  # noqa: F401

_I32 = np.dtype(np.int32).itemsize
_F32 = np.dtype(np.float32).itemsize


def volume_bytes(half: bool) -> int:
    """Bytes of one cost-volume element: 2 with half-precision storage
    (``-D VOL_HALF=1``, see kernels/common.h), else 4."""
    return 2 if half else 4


class WinnerTakeAll:
    """D(p) = argmin_d C(p, d) over valid cells; ties go to the smallest d.

    ``left(d_cost, D, H, W)`` gives D^L; ``right(d_cost, D, H, W)`` gives D^R
    from the same left-reference volume (the network is never rerun).
    """

    def __init__(self, ctx, half: bool = False, chunks: int | None = None):
        self.ctx = ctx
        # 16-pixel chunks per work-item of the left WTA (rule ``wta_chunks``; the same map at any)
        self.chunks = int(ctx.profile.rule("wta_chunks") if chunks is None else chunks)
        if self.chunks < 1:
            raise InputError(f"WTA chunks per work-item must be >= 1, got {self.chunks}")
        self.k_left = ctx.kernel("disparity.cl", "disparity_wta_left", VOL_HALF=int(half), WTA_CHUNKS=self.chunks)
        self.k_right = ctx.kernel("disparity.cl", "disparity_wta_right", VOL_HALF=int(half))

    def _run(self, kernel, stage, grid, d_cost, D, H, W, out):
        if out is None:
            out = self.ctx.empty(H * W * _I32, stage)
        launch(self.ctx, stage, kernel, grid, d_cost, out, np.int32(D), np.int32(H), np.int32(W))
        return out

    def left(self, d_cost, D, H, W, out=None):
        """D^L (int32 H x W buffer); 16 ``chunks`` pixels per work-item."""
        return self._run(self.k_left, "WTA (left)", (-(-W // (16 * self.chunks)), H), d_cost, D, H, W, out)

    def right(self, d_cost, D, H, W, out=None):
        """D^R (int32 H x W buffer), from the left-reference volume."""
        return self._run(self.k_right, "WTA (right)", (W, H), d_cost, D, H, W, out)


class RightReference:
    """The right image as the reference, from the left-reference volume (the
    network is never rerun).

    ``volume(d_cost, D, H, W)``: turns C_L into the right-reference volume
    mirrored left to right, in place: C_R'(d, y, x) = C_L(d, y, W-1-x+d) (NaN
    for d > x), which follows the left-reference conventions, so the cross
    arms, CBCA, SGM and WTA stages run on it unchanged with the mirrored right
    and left images as (left, right).  The mapping is its own inverse on the
    valid cells: a second call gives C_L back (its invalid cells d > x as
    NaN), so the pipeline holds no third volume for it.  ``mirror(d_map, H,
    W)`` mirrors an int32 map back.
    """

    def __init__(self, ctx, half: bool = False, lines=None):
        self.ctx = ctx
        # a work-item per (d, y) line, or per 16-pair block of one (rule ``mirror_lines``; the same bits)
        self.lines = bool(ctx.profile.rule("mirror_lines") if lines is None else lines)
        self.k_volume = ctx.kernel("disparity.cl", "disparity_right_volume", VOL_HALF=int(half),
                                   MIRROR_LINES=int(self.lines))
        self.k_mirror = ctx.kernel("disparity.cl", "disparity_mirror")

    def volume(self, d_cost, D, H, W):
        """Mirror ``d_cost`` (D x H x W) in place, C_L <-> C_R'; returns it."""
        grid = (H, D) if self.lines else (-(-W // 16), H, D)
        launch(self.ctx, "right-reference volume", self.k_volume, grid, d_cost, np.int32(D), np.int32(H), np.int32(W))
        return d_cost

    def mirror(self, d_map, H, W, out=None):
        if out is None:
            out = self.ctx.empty(H * W * _I32, "mirrored map")
        launch(self.ctx, "mirror", self.k_mirror, (W, H), d_map, out, np.int32(H), np.int32(W))
        return out


class LeftRightCheck:
    """Labels each pixel correct (0), mismatch (1) or occlusion (2).

    ``threshold``: |d - D^R(pd)| <= threshold counts as consistent; the
    paper's 1 (default).  The released code's ``< 1.1`` selects the same
    pixels on integer maps.  ``right_width``: columns of the real right image
    (default W, the real pair: nothing changes); in the working frame of a
    range with M < 0 the real cropped width, so that a candidate whose right
    pixel is the padding (x - d' >= right_width) is not one.
    """

    def __init__(self, ctx):
        self.ctx = ctx
        self.kernel = ctx.kernel("disparity.cl", "disparity_lr_check")

    def __call__(self, d_disp_l, d_disp_r, D, H, W, threshold=1.0, out=None, right_width=None):
        Wr = _right_width(W, right_width)
        if out is None:
            out = self.ctx.empty(H * W * _I32, "left-right check labels")
        launch(self.ctx, "left-right check", self.kernel, (W, H), d_disp_l, d_disp_r, out,
               np.int32(D), np.int32(H), np.int32(W), np.float32(threshold), np.int32(Wr))
        return out


class Interpolate:
    """D_INT: occlusions filled from the left (else right), mismatches with the
    upper median of the nearest correct pixels along 16 directions.

    ``directions``: ``"paper"`` (the 16 SGM directions, integer steps, walk
    stops at a correct pixel) or ``"code"`` (the released code: half-pixel
    steps, the walk stops at any pixel that is not a mismatch).
    ``first_column``: columns before it are not part of the image (the
    working frame's padding of a range with M < 0): a walk ends there as at
    the map's edge.  Default 0 (the real pair: nothing changes).
    """

    def __init__(self, ctx):
        self.ctx = ctx
        self.kernel = ctx.kernel("interpolate.cl", "interpolate_fill")
        self._dirs = {name: ctx.to_device(np.ascontiguousarray(v, np.float32))
                      for name, v in DIRECTIONS.items()}

    def __call__(self, d_disp, d_labels, H, W, directions="paper", out=None, first_column=0):
        if directions not in self._dirs:
            raise ValueError(f"directions must be one of {sorted(self._dirs)}, not {directions!r}")
        if not 0 <= int(first_column) < W:
            raise InputError(f"first_column must be in [0, {W}), not {first_column}")
        if out is None:
            out = self.ctx.empty(H * W * _I32, "D_INT")
        launch(self.ctx, "interpolation", self.kernel, (W, H), d_disp, d_labels, self._dirs[directions],
               out, np.int32(H), np.int32(W), np.int32(directions == "code"), np.int32(first_column))
        return out


class Subpixel:
    """D_SE = d - (C+ - C-) / (2 (C+ - 2C + C-)) at d = D_INT(p).

    ``min_denominator=0`` (the paper's: zero or negative curvature keeps d;
    released code: ``1e-5``).  ``clamp_step=True`` (the released code's
    behaviour and the matcher's default, ``Hyperparameters.subpixel_clamp``):
    the step is clamped to [-1, 1]; ``clamp_step=False`` gives the paper's
    formula unbounded.  d is kept at the range ends, where d+1 > x and where
    x - (d-1) >= ``right_width`` (a cell of the fit compares with a right
    pixel past the real right image: the working frame's padding of a range
    with M < 0; default W, the real pair, where that never holds).
    """

    def __init__(self, ctx, half: bool = False):
        self.ctx = ctx
        self.kernel = ctx.kernel("subpixel.cl", "subpixel_refine", VOL_HALF=int(half))

    def __call__(self, d_cost, d_disp, D, H, W, min_denominator=0.0, clamp_step=True, out=None,
                 right_width=None):
        Wr = _right_width(W, right_width)
        if out is None:
            out = self.ctx.empty(H * W * _F32, "D_SE")
        launch(self.ctx, "subpixel enhancement", self.kernel, (W, H), d_cost, d_disp, out,
               np.int32(D), np.int32(H), np.int32(W), np.float32(min_denominator), np.int32(bool(clamp_step)),
               np.int32(Wr))
        return out


def _right_width(W, right_width):
    """Columns of the real right image: W (None) or 1 .. W."""
    if right_width is None:
        return W
    if not 0 < int(right_width) <= W:
        raise InputError(f"right_width must be in [1, {W}], not {right_width}")
    return int(right_width)
