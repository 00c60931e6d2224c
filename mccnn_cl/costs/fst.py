"""MC-CNN-fst (JMLR 2016) on the device: :class:`FstCost`.

The tied conv stack (:class:`.features.ConvStack`) with ReLU *between* the
layers and none after the last, then each pixel's feature vector
L2-normalised, f / sqrt(|f|^2 + 1e-5) as in the released code, then the
cosine volume

    C(d, y, x) = -f_L(x, y) . f_R(x - d, y)      in [-1, 1],

NaN where x - d < 0 (``kernels/fst.cl``).  The released code runs its test
network with padding 1 so the features are image-sized; here the
convolutions are valid and the volume lives on the cropped domain (margin
m = (P - 1) / 2), like every other cost, so the pipeline treats all costs
alike.

Two volume kernels, bit for bit the same costs (each is 0, one fma per map
in increasing order, negated):

* ``fst_volume_pairs`` (``kernels/fst.cl``, the CPU form): a work-item per
  32 pixels of a row walking every disparity, its shifted right vectors
  loaded unaligned, on 16-wide vectors, or (``FST_VW`` 8: 16 pixels per
  work-item) made by shuffles of aligned loads on 8-wide ones, for CPUs whose
  vector registers hold 8 floats (rule ``fst_volume_width``: :meth:`DeviceProfile.fst_volume_width`;
  ``FstCost(volume_width=8 or 16)`` forces one);
* ``fst_volume_wg`` (``kernels/fst_wg.cl``, the "workgroup" path; the
  default on the profile's ``gpu`` column, rule ``fst_workgroup``): a
  work-group per (tile of TX columns, chunk of TD disparities, row) stages
  TK-map slices of the TX left and TX + TD - 1 right feature columns it
  needs in local memory, each work-item accumulating an RX x RD block of
  cells; two barriers per slice.  Each right feature is read from global
  memory once per group instead of once per disparity.  The tile starts
  from the profile's ``fst_volume_tile`` (64 x 64, TK 16, 4 x 4: 256
  work-items, 12224 bytes of local memory), TK capped by the maps, and shrinks
  (TD, then TX, then TK) to the kernel's CL_KERNEL_WORK_GROUP_SIZE, the
  item sizes and the local memory.  ``FstCost(workgroup=...)`` forces it
  (True, or a dict of sizes TX, TD, TK, RX, RD, checked) or excludes it.

The conv stack's GEMM has the same two shapes (``local_tiles=``, rule
``network_local_tiles``; :mod:`.features`), and on CPU devices its 3 x 3
layers run by Winograd's F(2x2, 3x3) (``winograd=``, rule ``network_winograd``).

Memory: the image is processed in bands of volume rows whose feature
buffers (both images, pixel-major and planar) take at most ``BAND_BYTES``
(fewer rows with a call's ``rows=``, as the stereo method's planner asks under
a tight ``memory_limit``);
the cost interface (``margin``, ``scratch_bytes``, ``__call__``,
``to_host``, ``flops``) is the one of :mod:`mccnn_cl.costs.registry`.
"""

from __future__ import annotations

import numpy as np

from ..opencl.context import BufferPool, launch_sizes, round_up
from ..errors import InputError
from ..weights import FST, Weights
from ..validate import check_cost_inputs
from .features import ConvNetCost, check_tile, fit_tile, normalise, shrinker

FST_CL = "fst.cl"
FST_WG_CL = "fst_wg.cl"
#: bytes of one band's feature buffers (both images) at most (``rows=`` may ask for fewer rows)
BAND_BYTES = 256 << 20
#: zero columns left of x = 0 in the planar features (kernels/fst.cl)
PADL = 32
#: pixels of a row per fst_volume_pairs work-item
_VOL_PX = 32


class FstCost(ConvNetCost):
    """Cosine cost volume of the fst network: ``FstCost(ctx, weights)(left, right, D)``.

    ``tiles``: the conv kernel's register tiles (:func:`.features.default_tiles`);
    ``half``: float16 volume storage; ``local_tiles``: the conv stack's GEMM
    path (:class:`.features.ConvStack`); ``workgroup``: the volume kernel
    (module docstring): None the profile's rule, False ``fst_volume_pairs``,
    True ``fst_volume_wg`` with the profile's tile, a dict ``fst_volume_wg``
    with those sizes.  ``volume_path`` says which ("workgroup" or "pairs"),
    ``volume_tile`` the work-group path's sizes.  ``winograd``: the conv
    stack's 3 x 3 layers by Winograd's F(2x2, 3x3) (None: the profile's
    rule; False: never; :class:`.features.ConvStack`).
    """

    architecture = FST
    local = False  # see mccnn_cl.costs.registry
    floor = -1.0  # lower bound of the cost: -cosine of unit vectors
    ceiling = 1.0
    label = "fst cost"

    def __init__(self, ctx, weights: Weights, tiles: dict | None = None, half: bool = False,
                 local_tiles=None, workgroup=None, volume_width: int | None = None, winograd=None):
        super().__init__(ctx, weights, tiles, half, local_tiles, winograd)
        self.nk = weights.feature_maps
        # the planar features of both images, kept between bands and calls like the conv
        # stack's maps: a fresh 100+ MB buffer's first write is page mapping on CPU devices
        self._planes = BufferPool(ctx)
        defs = dict(NK=self.nk, CS=self.stack.stride, PADL=PADL)
        wg = ctx.profile.local_tile("fst_workgroup", "fst_volume_tile", workgroup)
        self.volume_tile = None
        # the normalisation's form follows the volume's: 16 pixels per work-item beside the
        # CPU-shaped pairs form, one pixel per work-item beside the work-group form (GPUs)
        self._norm_px = 16 if wg is None else 1
        self._norm = ctx.kernel(FST_CL, "fst_normalise16" if wg is None else "fst_normalise", **defs)
        if wg is None:
            self.volume_path = "pairs"
            vw = ctx.profile.fst_volume_width() if volume_width is None else int(volume_width)
            if vw not in (8, 16):
                raise InputError(f"fst volume_width must be 8 or 16, got {vw}")
            self.volume_width = vw  # fst_volume_pairs built with FST_VW 16 or 8
            self._vol_px = 2 * vw
            self._vol = ctx.kernel(FST_CL, "fst_volume_pairs", VOL_HALF=int(half), FST_VW=vw, **defs)
        else:
            self.volume_path = "workgroup"
            self._vol, self.volume_tile = self._volume_wg(*wg)

    def _volume_wg(self, sizes, forced):
        """fst_volume_wg built with a tile that fits (:func:`.features.fit_tile`)."""
        check_tile(sizes, (("TX", "RX"), ("TD", "RD")), "fst volume")
        if not forced:
            sizes["TK"] = min(sizes["TK"], self.nk)
        # fewer disparities, then fewer columns, then fewer maps per slice
        shrink = shrinker(("TD", "RD"), ("TX", "RX"))
        defs = dict(NK=self.nk, PADL=PADL, VOL_HALF=int(self.half))
        return fit_tile(self.ctx, f"fst volume (NK={self.nk})", sizes, forced,
                        lambda t: 4 * t["TK"] * (2 * t["TX"] + t["TD"] - 1),
                        lambda t: (t["TX"] // t["RX"], t["TD"] // t["RD"]),
                        lambda t: self.ctx.kernel(FST_WG_CL, "fst_volume_wg", **defs, **t), shrink)

    def launch_volume(self, d_l, d_r, d_cost, h, w, y0, D, hb):
        """Enqueue the volume kernel: rows ``y0 .. y0 + hb - 1`` of the ``[D][h][w]``
        volume ``d_cost`` from the band's planar features ``d_l``, ``d_r``."""
        i32, t = np.int32, self.volume_tile
        args = (d_l, d_r, d_cost, i32(h), i32(w), i32(y0), i32(D), i32(self._wp(w)))
        if t is None:
            # rows of the band are not guarded (the kernel has no band height)
            self._vol(self.ctx.queue, *launch_sizes(self.ctx, (-(-w // self._vol_px), hb), guarded=(1, 0)), *args)
            return
        wx, wd = t["TX"] // t["RX"], t["TD"] // t["RD"]
        self._vol(self.ctx.queue, (-(-w // t["TX"]) * wx, -(-D // t["TD"]) * wd, hb), (wx, wd, 1), *args)

    def _wp(self, w: int) -> int:
        return PADL + round_up(w, 32)  # whole 32-pixel blocks of the pairs form inside a row

    def _row_bytes(self, w: int) -> int:
        """Feature bytes per volume row, both images (pixel-major of one at a time + planar)."""
        return (w * self.stack.stride + 2 * self.nk * self._wp(w)) * 4

    def band_rows(self, h: int, w: int) -> int:
        row = self._row_bytes(w)
        self.ctx.check_alloc(self.nk * self._wp(w) * 4, f"fst features of one row ({w} x {self.nk})")
        return max(1, min(h, min(BAND_BYTES // row, self.ctx.max_alloc // (self.nk * self._wp(w) * 4))))

    def scratch_bytes(self, h: int, w: int, rows=None) -> int:
        """Upper bound of the device bytes a call allocates besides the volume, for
        an h x w volume in bands of ``rows`` rows (:meth:`rows_of`): one band's
        planar features of both images, one pixel-major map, and the conv
        stack's two widest maps over the band."""
        rows = self.rows_of(h, w, rows)
        return rows * self._row_bytes(w) + self.stack.scratch_bytes(rows, w)

    def flops(self, height: int, width: int, max_disparity: int) -> dict:
        """Arithmetic of one volume for images of ``height`` x ``width`` (2 FLOP
        per multiply-add): ``features`` (the conv stack, both images),
        ``volume`` (a dot product of the maps per valid cell), ``total``."""
        feat, hh, ww = self.stack.flops(height, width, self.weights)
        valid = hh * sum(max(ww - d, 0) for d in range(int(max_disparity)))
        vol = 2 * self.nk * valid
        return {"features": feat, "volume": vol, "total": feat + vol, "valid_cells": valid}

    def to_host(self, *args, **kwargs):
        """:meth:`ConvNetCost.to_host`; the planar features are freed after it
        (the row tiles that follow hold volumes instead)."""
        try:
            return super().to_host(*args, **kwargs)
        finally:
            self._planes.clear()

    def _pools(self) -> list:
        return [self.stack._pool, self._planes]

    def _pooled_scratch(self, h: int, w: int, rows=None) -> list:
        """The conv stack's two maps and both images' planar features of one band."""
        plane = self.rows_of(h, w, rows) * self.nk * self._wp(w) * 4
        return super()._pooled_scratch(h, w, rows) + [plane, plane]

    def release_buffers(self) -> None:
        """Free the conv stack's kept maps (see ConvStack) and the kept planar features."""
        self.stack.release_buffers()
        self._planes.clear()

    def features(self, img):
        """Host copy of the normalised features of a whole image (h x w x maps,
        float32), for tests: the conv stack and fst_normalise."""
        I = check_cost_inputs(img, img, 1, self.channels, self.patch)[0]
        h, w = I.shape[0] - self.patch + 1, I.shape[1] - self.patch + 1
        d = self._features(normalise(I), h, w)
        wp = self._wp(w)
        out = self.ctx.from_device(d, (h, self.nk, wp))
        self._planes.give(d)
        return out[:, :, PADL:PADL + w].transpose(0, 2, 1).copy()

    def _features(self, band, hb, w, row0=0):
        d_feat = self.stack.run_image(band, row0)
        wp = self._wp(w)
        d_out = self._planes.take(hb * self.nk * wp * 4, "fst planar features")
        self._norm(self.ctx.queue, *launch_sizes(self.ctx, (wp // self._norm_px, hb), guarded=(1, 0)), d_feat,
                   d_out, np.int32(w), np.int32(wp))
        self.stack.give(d_feat)
        return d_out

    def _enqueue(self, L, R, D, h, w, rows, d_cost, progress, host=None, stats=None, row0=0):
        q, P = self.ctx.queue, self.patch
        Ln, Rn = self.standardised(L, R, stats)
        bands = range(0, h, rows)
        for i, y0 in enumerate(bands):
            hb = min(rows, h - y0)
            d_l = self._features(Ln[y0:y0 + hb + P - 1], hb, w, row0 + y0)
            d_r = self._features(Rn[y0:y0 + hb + P - 1], hb, w, row0 + y0)
            vh, vy0 = (h, y0) if host is None else (hb, 0)
            self.launch_volume(d_l, d_r, d_cost, vh, w, vy0, D, hb)
            if progress is not None or host is not None:
                self.ctx.finish()
            self._planes.give(d_l, d_r)  # the in-order queue runs their next writer after this volume
            if host is not None:
                band = np.empty((D, hb, w), self.vdtype)
                self.ctx.cl.enqueue_copy(q, band, d_cost)
                host[:, y0:y0 + hb, :] = band
            if progress is not None:
                progress(D * (i + 1) // len(bands), D)
