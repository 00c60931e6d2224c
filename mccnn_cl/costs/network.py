"""The fc networks as OpenCL kernels: :class:`PaperCost` (CVPR 2015, C_CNN)
and :class:`AcrtCost` (JMLR 2016 MC-CNN-acrt).

Both run the tied conv stack once per image (:class:`.features.ConvStack`,
``kernels/network_conv.cl``, or ``network_conv_wg.cl`` on the profile's
``gpu`` column; ReLU after every conv layer, the last too), then
the fc head per pixel and disparity.  Following the paper's "Matching cost"
section, the first fc layer (L4) acts on the concatenation
[f_L(p); f_R(p - d)], so with W4 = [W4a | W4b] it splits into two per-pixel
terms computed once,

    A(p) = W4a f_L(p) + b4,      B(q) = W4b f_R(q),

and the only per-disparity work is ReLU(A(p) + B(p - d)) followed by the
hidden layers (ReLU) and the output layer, fused in one kernel
(``network_head.cl``: a work-group per tile of TM cells of one disparity,
their activations in local memory), or on the profile's ``gpu`` column
(rule ``network_head_gemm``) layer by layer (``network_head_wg.cl``: runs
of up to :data:`GEMM_CELLS` cells of a disparity with their activations in
global memory, each hidden layer one GEMM of the conv stack's kernel as a
1 x 1 convolution, local-memory tiles on GPUs), which lets a GPU reuse
each weight over a 64-cell tile instead of the few cells whose
activations fit its local memory.  Both form every unit from the same
float operations in the same order (and the last layer is one shared
function, ``network_out.h``), so their volumes are equal bit for bit (with
the same register tiles: the last layer sums RN lanes).
The output layer is the one difference between the networks: the paper's
has 2 logits and a softmax, cost = P(bad match) = softmax[0] (``NOUT=2``);
acrt's has 1 output through a sigmoid, cost = that output (``NOUT=1``; the
released code trains it towards 0 on matches).  Both costs lie in [0, 1].

Volume: ``[D][H][W]`` with H = H_img - 2m, W = W_img - 2m (m the margin);
cell (d, y, x) compares the left patch centred at image (x + m, y + m) with
the right one at (x + m - d, y + m); NaN where x - d < 0.  Memory: the image
is processed in bands of volume rows (A and B of one band at most
``BAND_BYTES`` each; fewer rows when the caller passes ``rows=``, as the
stereo method's planner does under a tight ``memory_limit``), each band's
disparities in chunks of about
``CHUNK_CELLS`` cells per launch.  The cost interface shared with census and
fst: :mod:`mccnn_cl.costs.registry`.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ..opencl.context import launch_sizes, round_up
from ..errors import InputError
from ..weights import ACRT, PAPER, Weights
from .features import ConvNetCost, normalise  # noqa: F401 (normalise re-exported)

log = logging.getLogger(__name__)

HEAD_CL = "network_head.cl"
HEAD_WG_CL = "network_head_wg.cl"

#: Cells per run of the "gemm" head (its two activation buffers hold
#: this many cells x HP floats each: 100 MB at HP = 384).
GEMM_CELLS = 1 << 16

# Cells (pixel-disparity pairs) per head launch, roughly: disparities are
# processed in chunks of about this many cells so one launch stays short
# (progress reporting, GPU watchdogs) while launches stay large.
CHUNK_CELLS = 1 << 20

# Bytes of one band's A (and of its B) at most: the image is processed in bands
# of volume rows so scratch memory stays bounded whatever the image size (a
# call's ``rows=`` may ask for fewer rows: ConvNetCost.rows_of).
BAND_BYTES = 256 << 20


class PaperCost(ConvNetCost):
    """The paper's network on the device: ``PaperCost(ctx, weights)(left, right, D) -> d_cost``.

    Parameters
    ----------
    ctx : ClContext
    weights : Weights
        A network of the paper's family (sizes are read from it): conv
        layers, then fc layers ending in 2 outputs (:class:`AcrtCost`: 1).
    tiles : dict, optional
        Overrides of the tile sizes (``TM`` cells per head work-group, ``RM``
        x ``RN`` register micro-tile, ``ROWS_FASTEST`` work-item order,
        ``CONV_RM`` pixels per work-item of the conv kernel); by default they
        are chosen from the device type and shrunk until the head kernel's
        local memory and work-group size fit the device.
    half : bool
        float16 volume storage.
    local_tiles : None, bool or dict
        The GEMM kernel of the conv layers and the L4 split (None: the
        profile's ``network_local_tiles`` rule; see :class:`.features.ConvStack`).
    head_gemm : None or bool
        The head's layout (module docstring): True layer by layer through
        the conv stack's GEMM ("gemm"), False fused (``network_head``),
        None the profile's ``network_head_gemm`` rule.  ``head_path`` says which.
    winograd : None, False or (RT, XA)
        The 3 x 3 conv layers by Winograd's F(2x2, 3x3) (None: the
        profile's ``network_winograd`` rule; see :class:`.features.ConvStack`).

    Calls as every cost (:class:`.features.ConvNetCost`): scratch memory is
    bounded, the image being processed in bands of volume rows whose A and B
    buffers take at most ``BAND_BYTES`` each (the feature maps of a band are
    smaller); each band's input rows overlap the next band's by P - 1 rows,
    so the band seams are exact.
    """

    architecture = PAPER
    stack_rn_from_head = True  # the L4 split is a conv-stack kernel of the head's width
    #: per-tile cost (see mccnn_cl.costs.registry): False, the volume is
    #: computed once for the whole image (into host memory when tiled)
    local = False
    #: lower and upper bound of the cost (a softmax or sigmoid probability)
    floor = 0.0
    ceiling = 1.0
    label = "network (C_CNN)"

    def __init__(self, ctx, weights: Weights, tiles: dict | None = None, half: bool = False,
                 local_tiles=None, head_gemm: bool | None = None, winograd=None):
        super().__init__(ctx, weights, tiles, half, local_tiles, winograd)
        gemm = bool(ctx.profile.rule("network_head_gemm") if head_gemm is None else head_gemm)
        self.head_path = "gemm" if gemm else "fused"
        self._runs = None  # the "gemm" head's (cells, [two activation buffers]), kept between calls
        t = self.tiles
        rn = self.rn = self.stack.rn
        cs = self.feat_stride = self.stack.stride
        maps = weights.feature_maps

        # -- fc layers: L4 split, hidden layers, last layer ------------------
        fc = weights.fc
        hidden_out = [W.shape[0] for W, _ in fc[:-1]]
        self.hp = hp = round_up(max(hidden_out), rn)
        self.nhid = nhid = len(fc) - 2
        W4, b4 = fc[0]
        n4 = W4.shape[0]
        wa = np.zeros((maps, hp), np.float32)
        wb = np.zeros((maps, hp), np.float32)
        wa[:, :n4] = W4[:, :maps].T
        wb[:, :n4] = W4[:, maps:].T
        ba = np.zeros(hp, np.float32)
        ba[:n4] = b4
        self._split_kernel = self.stack.kernel(1, maps, cs, hp, relu=0)
        self._d_wa, self._d_wb = ctx.to_device(wa), ctx.to_device(wb)
        self._d_ba, self._d_bzero = ctx.to_device(ba), ctx.to_device(np.zeros(hp, np.float32))
        wh = np.zeros((max(nhid, 1), hp, hp), np.float32)
        bh = np.zeros((max(nhid, 1), hp), np.float32)
        for l, (W, b) in enumerate(fc[1:-1]):
            wh[l, :W.shape[1], :W.shape[0]] = W.T
            bh[l, :W.shape[0]] = b
        W8, b8 = fc[-1]
        self.nout = nout = W8.shape[0]  # 2: softmax (paper), 1: sigmoid (acrt)
        w8 = np.zeros((nout, hp), np.float32)
        w8[:, :W8.shape[1]] = W8
        self._d_w8, self._d_b8 = ctx.to_device(w8), ctx.to_device(np.asarray(b8, np.float32))
        if gemm:  # the hidden layers as 1 x 1 convolutions of [cells][HP] maps, one weight buffer each
            self._hidden = self.stack.kernel(1, hp, hp, hp, relu=1)
            self._d_layers = [(ctx.to_device(wh[l]), ctx.to_device(bh[l])) for l in range(nhid)]
            defs = dict(HP=hp, RN=rn, NOUT=nout, VOL_HALF=int(half))
            self._l4 = ctx.kernel(HEAD_WG_CL, "network_head_l4", **defs)
            self._out = ctx.kernel(HEAD_WG_CL, "network_head_out", **defs)
            self.tm, self.rm, self.nwi = 1, 1, 1  # the fused head's tile: only its NaN marking is used
            self._mark = ctx.kernel(HEAD_CL, "network_mark_invalid", HP=hp, NHID=nhid, TM=1, RM=1, RN=rn,
                                    ROWS_FASTEST=0, VOL_HALF=int(half), NOUT=nout)
            log.info("network: HP=%d NHID=%d RN=%d, head layer by layer (runs of %d cells, conv path %s)",
                     hp, nhid, rn, GEMM_CELLS, self.stack.path)
            return

        # the fused head reads the hidden layers from one buffer (the "gemm" head one per layer, above)
        self._d_wh, self._d_bh = ctx.to_device(wh), ctx.to_device(bh)

        # -- head kernel: shrink the tile until local memory and group size fit
        tm, rm = int(t["TM"]), int(t["RM"])
        if tm < 1 or rm < 1 or tm % rm:
            raise InputError(f"tile TM={tm} must be a positive multiple of RM={rm}")
        ncg = hp // rn
        while True:
            if 2 * tm * hp * 4 <= ctx.local_mem:
                kern = ctx.kernel(HEAD_CL, "network_head", HP=hp, NHID=nhid, TM=tm, RM=rm, RN=rn,
                                  ROWS_FASTEST=int(t["ROWS_FASTEST"]), VOL_HALF=int(half), NOUT=nout)
                max_wg = ctx.work_group_size(kern)
                kl = int(kern.get_work_group_info(ctx.cl.kernel_work_group_info.LOCAL_MEM_SIZE,
                                                  ctx.device))
                if kl <= ctx.local_mem and tm // rm <= max_wg:
                    break
            if tm > rm:
                tm = max(rm, (tm // 2) // rm * rm)
            elif rm > 1:
                rm //= 2
                tm = rm
            else:
                raise InputError(
                    f"the network's hidden width {hp} does not fit this device's local memory "
                    f"({ctx.local_mem} bytes) even with 1-row tiles")
        nrg = tm // rm
        self.tm, self.rm = tm, rm
        self.nwi = nrg * min(ncg, max_wg // nrg)  # work-items: all row groups x column groups
        self._head = kern
        self._mark = ctx.kernel(HEAD_CL, "network_mark_invalid", HP=hp, NHID=nhid, TM=tm, RM=rm,
                                RN=rn, ROWS_FASTEST=int(t["ROWS_FASTEST"]), VOL_HALF=int(half), NOUT=nout)
        log.info("network: HP=%d NHID=%d TM=%d RM=%d RN=%d (%d work-items, %d B local)",
                 hp, nhid, tm, rm, rn, self.nwi, 2 * tm * hp * 4)

    # ---------------------------------------------------------------------
    def features(self, d_img, H: int, W: int):
        """The conv layers (ReLU after each) over an uploaded image, fully
        convolutionally: a new buffer ``[(H-P+1) * (W-P+1)][feat_stride]``
        (see :class:`.features.ConvStack`)."""
        return self.stack(d_img, H, W)

    def release_buffers(self) -> None:
        """Free the conv stack's kept maps (see ConvStack) and the "gemm" head's activations."""
        self.stack.release_buffers()
        self._free_runs()

    def _free_runs(self) -> None:
        for buf in self._runs[1] if self._runs else ():
            buf.release()
        self._runs = None

    def split_l4(self, d_feat, n_pixels: int, left: bool):
        """The L4 split of L3 features: ``A = W4a f + b4`` (left) or ``B = W4b f`` (right).

        Returns a new device buffer ``[n_pixels][hp]`` (no ReLU: it is applied
        to ``A(p) + B(p - d)`` in the head).
        """
        d_out = self.ctx.empty(int(n_pixels) * self.hp * 4, "network L4 split")
        d_w, d_b = (self._d_wa, self._d_ba) if left else (self._d_wb, self._d_bzero)
        self.stack.launch(self._split_kernel, d_feat, n_pixels, d_w, d_b, d_out, n_pixels,
                          n_pixels, self.hp)
        return d_out

    def _half(self, band: np.ndarray, left: bool, row0: int = 0):
        """Upload a normalised float32 image band (rows x W x C) and run it through
        L1-L3 and its half of L4; returns the ``[pixels][hp]`` buffer A or B."""
        H, W = band.shape[:2]
        d_feat = self.stack.run_image(band, row0)
        n = (H - self.patch + 1) * (W - self.patch + 1)
        d_half = self.split_l4(d_feat, n, left=left)
        self.stack.give(d_feat)
        return d_half

    def flops(self, height: int, width: int, max_disparity: int) -> dict:
        """Arithmetic of one cost volume for images of ``height`` x ``width``
        (2 FLOP per multiply-add, unpadded layer sizes): ``features`` (conv
        layers and the L4 split, both images), ``head`` (per valid cell
        x >= d: L4 add, the hidden layers, the last layer), ``total``."""
        wts = self.weights
        feat, hh, ww = self.stack.flops(height, width, wts)  # valid convolutions, both images
        n4 = wts.fc[0][0].shape[0]
        feat += 2 * 2 * hh * ww * wts.feature_maps * n4           # A and B
        per_cell = n4 + sum(2 * W.shape[0] * W.shape[1] for W, _ in wts.fc[1:])
        D = int(max_disparity)
        valid = hh * sum(max(ww - d, 0) for d in range(D))
        return {"features": feat, "head": valid * per_cell, "total": feat + valid * per_cell,
                "valid_cells": valid}

    def scratch_bytes(self, h: int, w: int, rows=None) -> int:
        """Upper bound of the device bytes a call allocates besides the volume,
        for a volume of h x w pixels in bands of ``rows`` rows (:meth:`rows_of`):
        one band's A and B, and two feature maps of the widest layer over the
        band's image rows (input and output of a convolution)."""
        rows = self.rows_of(h, w, rows)
        widest = max(self.stack.widest, self.hp)
        gemm = 2 * min(GEMM_CELLS, rows * w) * self.hp * 4 if self.head_path == "gemm" else 0
        return 2 * rows * w * self.hp * 4 + 2 * (rows + self.patch) * (w + self.patch - 1) * widest * 4 + gemm

    def band_rows(self, h: int, w: int) -> int:
        """Volume rows per band: A and B of one band take at most BAND_BYTES each."""
        row = w * self.hp * 4
        self.ctx.check_alloc(row, f"network L4 split of one row ({w} x {self.hp})")
        return max(1, min(h, min(BAND_BYTES, self.ctx.max_alloc) // row))

    def _enqueue(self, L, R, D, h, w, rows, d_cost, progress, host=None, stats=None, row0=0):
        """The launches of :meth:`__call__` (inputs already checked).  With
        ``host`` (a [D][h][w] array), ``d_cost`` holds one band at a time
        ([D][hb][w]), copied into ``host`` after each band."""
        q = self.ctx.queue
        P = self.patch
        i32 = np.int32
        if host is None:  # NaN into every invalid cell (x < d) of the volume, once
            self._mark(q, *launch_sizes(self.ctx, (w, h, D), guarded=(1, 1, 0)), d_cost, i32(h), i32(w), i32(0))
        Ln, Rn = self.standardised(L, R, stats)
        bands = range(0, h, rows)
        done = 0
        for y0 in bands:
            hb = min(rows, h - y0)
            # the volume the head writes into: whole (rows y0 ..), or this band alone
            vh, vy0 = (h, y0) if host is None else (hb, 0)
            if host is not None:
                self._mark(q, *launch_sizes(self.ctx, (w, hb, D), guarded=(1, 1, 0)), d_cost, i32(hb), i32(w), i32(0))
            d_a = self._half(Ln[y0:y0 + hb + P - 1], left=True, row0=row0 + y0)
            d_b = self._half(Rn[y0:y0 + hb + P - 1], left=False, row0=row0 + y0)
            per_chunk = max(1, min(D, CHUNK_CELLS // max(1, hb * w)))
            for d0 in range(0, D, per_chunk):
                nd = min(per_chunk, D - d0)
                n_valid = hb * max(w - d0, 0)
                if self.head_path == "gemm":
                    self._gemm_head(d_a, d_b, d_cost, vh, w, vy0, hb, range(d0, d0 + nd))
                elif n_valid > 0:
                    tiles = math.ceil(n_valid / self.tm)
                    self._head(q, (tiles * self.nwi, nd), (self.nwi, 1),
                               d_a, d_b, self._d_wh, self._d_bh, self._d_w8, self._d_b8, d_cost,
                               i32(vh), i32(w), i32(vy0), i32(hb), i32(d0))
                done += nd
                # at most about two chunks queued ahead (~1 s each on a CPU):
                # Ctrl-C is answered within seconds (ClContext.pace)
                self.ctx.pace()
                if progress is not None:
                    self.ctx.finish()
                    progress(done // len(bands), D)
            self.ctx.finish()
            d_a.release()
            d_b.release()
            if host is not None:
                band = np.empty((D, hb, w), self.vdtype)
                self.ctx.cl.enqueue_copy(q, band, d_cost)
                host[:, y0:y0 + hb, :] = band

    def _gemm_head(self, d_a, d_b, d_cost, h, w, y0, hb, disparities):
        """The "gemm" head (kernels/network_head_wg.cl) for the valid cells of
        ``disparities`` in a band (A, B of its rows): runs of up to
        GEMM_CELLS cells through L4, the hidden layers (the conv stack's GEMM,
        1 x 1) and the last layer."""
        if self._runs is None or self._runs[0] < min(GEMM_CELLS, hb * w):
            n = min(GEMM_CELLS, hb * w)
            self._free_runs()
            self._runs = (n, [self.ctx.empty(n * self.hp * 4, "network head activations") for _ in range(2)])
        n_max, acts = self._runs
        q, i32, hp, rn = self.ctx.queue, np.int32, self.hp, self.rn
        for d in disparities:
            n_valid = hb * max(w - d, 0)
            for c0 in range(0, n_valid, n_max):
                n = min(n_max, n_valid - c0)
                # launch_sizes: n follows the image width and the disparity, so on PoCL a
                # work-group size left to the runtime was a new compile of both kernels
                # for nearly every n (both return beyond n)
                self._l4(q, *launch_sizes(self.ctx, (hp // rn, n)), d_a, d_b, acts[0], i32(w), i32(d), i32(c0),
                         i32(n))
                for l, (d_w, d_bias) in enumerate(self._d_layers):
                    self.stack.launch(self._hidden, acts[l & 1], n, d_w, d_bias, acts[(l + 1) & 1], n, n, hp)
                self._out(q, *launch_sizes(self.ctx, (n,)), acts[self.nhid & 1], self._d_w8, self._d_b8, d_cost,
                          i32(h), i32(w), i32(y0), i32(d), i32(c0), i32(n))

    def compute(self, left, right, max_disparity) -> np.ndarray:
        """Host copy of :meth:`__call__`: array ``[D][H_img-8][W_img-8]`` (float32,
        float16 with half storage)."""
        L = np.asarray(left)
        d = self(left, right, max_disparity)
        h, w = L.shape[0] - self.patch + 1, L.shape[1] - self.patch + 1
        out = self.ctx.from_device(d, (int(max_disparity), h, w), self.vdtype)
        d.release()
        return out


class AcrtCost(PaperCost):
    """MC-CNN-acrt (JMLR 2016) on the device: the paper's structure (ReLU after
    every conv layer, L4 split, hidden fc layers with ReLU) with 1 output
    through a sigmoid; cost = that output, P(bad match) in [0, 1]."""

    architecture = ACRT


#: the name this stage had before fst and acrt existed
NetworkCost = PaperCost
