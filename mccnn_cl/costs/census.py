"""Census matching cost: ``kernels/census.cl``.

A classical cost so that the whole stereo method runs without trained
weights: 9 x 9 census transform (bit set when the neighbour is darker than the
centre) of both images, cost = Hamming distance / 80 in [0, 1] (like the
network's P(bad match)), on the network's cropped domain (margin 4, so the
volumes are interchangeable), NaN where x - d < 0.

``CensusCost(ctx)(left, right, max_disparity) -> d_cost`` takes host gray
float32 images (any scale; only the order of intensities matters).  Numpy twin:
:func:`mccnn_cl.reference.disparity.census_cost`.  The cost interface it
shares with the networks: :mod:`mccnn_cl.costs.registry`.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..opencl.context import launch, round_up
from ..stages.disparity import volume_bytes
from .base import MatchingCost

MARGIN = 4
WINDOW = 2 * MARGIN + 1


class CensusCost(MatchingCost):
    """Census + Hamming cost volume (float32, D x (H_img - 8) x (W_img - 8))."""

    kind = "census"
    margin = MARGIN
    local = True  # a row tile's volume needs only the tile's rows (mccnn_cl.costs.registry)
    floor = 0.0  # lower bound of the cost: a Hamming distance
    ceiling = float(WINDOW * WINDOW - 1)  # ... of WINDOW^2 - 1 bits

    def __init__(self, ctx, half: bool = False, launch_shape=None):
        """``launch_shape``: (levels per work-item, 0 = all; work-group size or
        None) of the cost kernel, None: the device's RULES row
        ``census_cost_launch``; every shape gives the same bits."""
        self.ctx = ctx
        self.half = bool(half)
        self.launch_shape = ctx.profile.rule("census_cost_launch") if launch_shape is None else launch_shape
        self.vdtype = np.dtype(np.float16 if half else np.float32)
        self.k_transform = ctx.kernel("census.cl", "census_transform")
        self.k_cost = ctx.kernel("census.cl", "census_cost", VOL_HALF=int(half))

    @classmethod
    def build(cls, ctx, weights, half: bool = False, tiles: dict | None = None):
        """No weights, no tiles: ``CensusCost(ctx, half)``."""
        return cls(ctx, half=half)

    @staticmethod
    def scratch_bytes(H: int, W: int, rows=None) -> int:
        """Device bytes a call allocates besides the volume: the two images'
        census bits (3 words per pixel) on the H x W cost-volume domain
        (``rows``: ignored, census is computed in one launch)."""
        return 2 * 3 * int(H) * int(W) * 4

    def release_buffers(self) -> None:
        """Nothing is kept between calls (the interface of mccnn_cl.costs.registry)."""

    @staticmethod
    def flops(height: int, width: int, max_disparity: int) -> dict:
        """Operations of one volume, counted as 2 per census comparison and 2 per
        Hamming word (popcount + add) per cell: a rough figure for reports."""
        h, w, D = int(height) - 2 * MARGIN, int(width) - 2 * MARGIN, int(max_disparity)
        transform = 2 * 2 * h * w * (WINDOW * WINDOW - 1)
        volume = 2 * 3 * D * h * w
        return {"transform": transform, "volume": volume, "total": transform + volume}

    def to_host(self, left, right, max_disparity, max_bytes=None, progress=None, stats=None, rows=None, row0=0):
        """The volume as a host array (computed on the device, then copied)."""
        if not isinstance(left, np.ndarray):
            raise InputError("census to_host needs host images")
        d = self(left, right, max_disparity)
        H, W = left.shape[0] - 2 * MARGIN, left.shape[1] - 2 * MARGIN
        out = self.ctx.from_device(d, (int(max_disparity), H, W), self.vdtype)
        d.release()
        return out

    def __call__(self, left, right, max_disparity, out=None, progress=None, stats=None, scratch=None, rows=None,
                 row0=0):
        """Cost volume of the host images ``left`` vs ``right``; ``progress`` is
        accepted as every cost's and not called (one launch), so are ``stats``
        (census compares intensities, it standardises nothing), ``scratch``
        (its bit planes are small: 16 bytes a pixel), ``rows`` (no bands) and ``row0``
        (its sums do not depend on where a tile starts)."""
        if not (isinstance(left, np.ndarray) and isinstance(right, np.ndarray)):
            raise InputError("census needs host images (numpy arrays)")
        if left.shape != right.shape or left.ndim != 2:
            raise InputError(f"census needs two gray images of one size, got {left.shape} and {right.shape}")
        shape = left.shape
        d_left = self.ctx.to_device(left.astype(np.float32))
        d_right = self.ctx.to_device(right.astype(np.float32))
        Hi, Wi = (int(s) for s in shape)
        H, W, D = Hi - 2 * MARGIN, Wi - 2 * MARGIN, int(max_disparity)
        if H < 1 or W < 1:
            raise InputError(f"image {Wi}x{Hi} is smaller than the {WINDOW}x{WINDOW} census window")
        if D < 1:
            raise InputError(f"max_disparity must be >= 1, not {D}")
        nbits = 3 * H * W * 4
        d_bits_l = self.ctx.empty(nbits, "census bits (left)")
        d_bits_r = self.ctx.empty(nbits, "census bits (right)")
        for d_img, d_bits in ((d_left, d_bits_l), (d_right, d_bits_r)):
            launch(self.ctx, "census transform", self.k_transform, (W, H), d_img, d_bits,
                   np.int32(H), np.int32(W))
        if out is None:
            out = self.ctx.empty(D * H * W * volume_bytes(self.half), "census cost volume")
        # a work-item: 16 columns x `levels` levels (RULES "census_cost_launch")
        levels, local = self.launch_shape
        levels = D if int(levels) <= 0 else min(int(levels), D)
        glob = (-(-W // 16), H, -(-D // levels))
        if local is not None:
            glob = tuple(round_up(g, int(n)) for g, n in zip(glob, local))
        launch(self.ctx, "census cost", self.k_cost, glob, d_bits_l, d_bits_r, out,
               np.int32(D), np.int32(H), np.int32(W), np.int32(levels), local_size=local)
        return out
