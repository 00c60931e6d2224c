"""The siamese conv stack shared by every network: :class:`ConvStack`.

All three architectures (paper, fst, acrt) start with the same tower: valid
KS x KS convolutions of the standardised gray image, run once per image,
fully convolutionally, as one GEMM per layer over output pixels.  The
towers differ only in whether a ReLU follows the last layer (paper and
acrt: yes; fst: no, its features are L2-normalised next).  Layer count,
maps and kernel sizes are read from the weights.

Two kernels compute that GEMM, with the same float operations per output
(bias, one fma per term in the same order, ReLU), so bit for bit the same:

* ``kernels/network_conv.cl`` (``network_conv``): register blocks, no
  local memory; a work-item computes CONV_RM pixels x RN channels reading
  its operands from global memory (CPUs: the caches do the reuse);
* ``kernels/network_conv_wg.cl`` (``network_conv_wg``, the "local tiles"
  path; the default on the profile's ``gpu`` column, rule
  ``network_local_tiles``): a work-group per TM x TN tile of outputs stages
  TK-term slices of both operands in local memory (the input gathered
  im2col-style on the fly), each work-item accumulating an RM x RN register
  block; two barriers per slice.  The tile starts from the profile's
  ``network_gemm_tile`` (64 x 64, TK 16, 4 x 4: 256 work-items, 8704 bytes of
  local memory), TN and TK capped by the layer's channels and terms, and
  shrinks (TM, then TN, then TK) until the group fits the kernel's
  CL_KERNEL_WORK_GROUP_SIZE, the device's item sizes and its local memory.
  ``ConvStack(local_tiles=...)`` forces it (True, or a dict of sizes,
  checked: InputError when they do not fit) or excludes it (False).

On CPU devices the 3 x 3 layers whose input channels are a multiple of RN
run by Winograd's F(2x2, 3x3) instead (``kernels/network_conv_wino.cl``,
rule ``network_winograd``: 2.25x fewer multiplies, ~1.5x faster a layer;
the first layer, one channel, stays direct).  Its sums are ordered
differently: its features equal the direct kernels' to float32 rounding
(both within ~1e-6 of a float64 convolution), not bit for bit, and a map
cut at an odd row (a band, a row tile) is computed on the whole map's tile
grid (``row0``), so bands and row tiles still give the whole image's
values bit for bit.

Layouts: the image is float32 ``[H][W][C]``; each layer's output is
channel-last, pixel-major ``[(H - ks + 1) * (W - ks + 1)][NP]`` with NP the
layer's maps padded to the vector width RN (padded channels hold exactly 0:
zero weights, zero bias).  The stack's output is the last layer's map on
``(H - P + 1) x (W - P + 1)`` pixels, P = the patch size.

Also here: :func:`normalise`, the per-image standardisation the networks see
(and that the stereo method's thresholds compare with
``intensity_scale="standardised"``), and :class:`ConvNetCost`, the base of
the network costs: their common state and the banded volume's two entry
points (inputs checked by :func:`mccnn_cl.validate.check_cost_inputs`).
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np

from ..opencl.context import Arena, BufferPool, launch_sizes, round_up
from ..errors import InputError, OpenCLError, WeightsError
from ..validate import check_cost_inputs
from ..imageops import standardise as normalise  # noqa: F401 (one standardisation: training's too)
from .base import MatchingCost

CONV_CL = "network_conv.cl"
CONV_WG_CL = "network_conv_wg.cl"
CONV_WINO_CL = "network_conv_wino.cl"
#: network_conv_wg's tile dimensions and their register blocks, in shrinking order
CONV_BLOCKS = (("TM", "RM"), ("TN", "RN"))

#: One layer's GEMM kernel: ``tile`` None for network_conv (register blocks),
#: else the sizes network_conv_wg was built with (TM, TN, TK, RM, RN).
ConvKernel = namedtuple("ConvKernel", "kern tile wino", defaults=(None,))

#: Winograd F(2x2, 3x3)'s weight transform: U = G g G^T per (output, input) pair
WINO_G = np.array([[1, 0, 0], [.5, .5, .5], [.5, -.5, .5], [0, 0, 1]], np.float64)


def winograd_weights(W, npad: int) -> np.ndarray:
    """U = G g G^T of every (output, input) pair of 3 x 3 kernels ``W`` [cout][cin][3][3]
    (computed in float64), as network_conv_wino reads it: float32 [16][cin][npad] (a run
    over the input channels contiguous, kernels/network_conv_wino.cl), the padded outputs
    zero."""
    cout, cin = W.shape[:2]
    U = np.zeros((16, cin, int(npad)), np.float32)
    u = np.einsum("ai,kcij,bj->cabk", WINO_G, np.asarray(W, np.float64), WINO_G).reshape(cin, 16, cout)
    U[:, :, :cout] = u.transpose(1, 0, 2)
    return U


def launch_winograd(ctx, kern, rt: int, rn: int, d_in, w_in: int, d_u, d_b, d_out, w_out: int, h_out: int,
                    npad: int, row0: int = 0) -> None:
    """Enqueue network_conv_wino (built with RT ``rt``, RN ``rn``, NP ``npad``): the valid 3 x 3
    layer of a ``(h_out + 2) x w_in`` map into ``h_out x w_out`` outputs, on the tile grid of
    the whole map whose row ``row0`` is this map's first (``d_u``: :func:`winograd_weights`)."""
    p = int(row0) % 2
    tw, th = (int(w_out) + 1) // 2, (int(h_out) + p + 1) // 2
    g = int(npad) // int(rn)
    kern(ctx.queue, (g, -(-tw // int(rt)), th), (g, 1, 1), d_in, np.int32(w_in), np.int32(h_out + 2), d_u, d_b,
         d_out, np.int32(w_out), np.int32(h_out), np.int32(tw), np.int32(th), np.int32(p))


def winograd_local_bytes(cin: int, npad: int, rn: int, rt: int) -> int:
    """Local memory of a network_conv_wino work-group: RT tiles' 16 transformed patches
    (CIN, each tile padded by 16 floats), shared by the group, and per channel group the
    tiles' products (RN)."""
    return rt * (16 * cin + 16 + (npad // rn) * 16 * rn) * 4


def fit_tile(ctx, what, sizes, forced, local_bytes, local_size, build, shrink):
    """Build a local-memory tiled kernel whose work-group fits the device.

    ``sizes``: the tile (a dict); ``local_bytes(sizes)``: its local memory;
    ``local_size(sizes)``: its 2-D work-group; ``build(sizes)``: the kernel;
    ``shrink(sizes)``: a smaller tile or None.  A tile fits when its local
    memory is within the device's, and its work-group within the kernel's
    CL_KERNEL_WORK_GROUP_SIZE and the device's item sizes; forced tiles are
    not shrunk.  Returns ``(kernel, sizes)``; InputError when nothing fits."""
    dims = [int(n) for n in ctx.device.max_work_item_sizes]
    while True:
        need = local_bytes(sizes)
        if need > ctx.local_mem:
            problem = f"{need} bytes of local memory, more than the device's {ctx.local_mem}"
        else:
            kern = build(sizes)
            l0, l1 = local_size(sizes)
            kmax = ctx.work_group_size(kern)
            kl = int(kern.get_work_group_info(ctx.cl.kernel_work_group_info.LOCAL_MEM_SIZE, ctx.device))
            if l0 * l1 > kmax or l0 > dims[0] or l1 > dims[1]:
                problem = f"work-groups of {l0} x {l1} work-items, more than the kernel's maximum {kmax}"
            elif kl > ctx.local_mem:
                problem = f"{kl} bytes of local memory, more than the device's {ctx.local_mem}"
            else:
                return kern, sizes
        smaller = None if forced else shrink(dict(sizes))
        if smaller is None:
            raise InputError(f"{what} tile {sizes} needs {problem} on {ctx.describe()}")
        sizes = smaller


def halve_tile(sizes, key, unit):
    """A tile's shrinking step: ``sizes`` with ``key`` halved, rounded down to a
    multiple of ``sizes[unit]`` (its register block); None when already at it."""
    if sizes[key] <= sizes[unit]:
        return None
    sizes[key] = max(sizes[unit], sizes[key] // 2 // sizes[unit] * sizes[unit])
    return sizes


def shrinker(*blocks):
    """A tile's shrink step for :func:`fit_tile`: halve the first of ``blocks``
    (``(key, register-block key)`` pairs, in order) that can still shrink,
    else halve TK (the terms per slice); None when nothing can."""
    def shrink(t):
        for key, unit in blocks:
            if halve_tile(t, key, unit):
                return t
        if t["TK"] > 1:
            t["TK"] //= 2
            return t
        return None
    return shrink


def check_tile(sizes, pairs, what):
    """InputError unless every size is >= 1 and each ``(big, small)`` of ``pairs``
    (a tile and its register block) divides."""
    for key in sizes:
        if int(sizes[key]) < 1:
            raise InputError(f"{what} tile sizes must be >= 1, got {sizes}")
    for big, small in pairs:
        if sizes[big] % sizes[small]:
            raise InputError(f"{what} tile: {big}={sizes[big]} must be a multiple of {small}={sizes[small]}")


def default_tiles(ctx) -> dict:
    """Starting tile sizes for a device (refined against its limits by the costs):
    the profile's ``network_tiles`` rule (:mod:`mccnn_cl.opencl.device`)."""
    return ctx.profile.network_tiles()


#: pixel groups per work-group of the register-tile conv kernel where the device
#: takes fixed work-group sizes (:func:`mccnn_cl.opencl.context.launch_sizes`)
CONV_ROWS_LOCAL = 8


class ConvStack:
    """The tied conv layers on the device: ``ConvStack(ctx, weights, rn, conv_rm)``.

    ``relu_after_last`` defaults to ``weights.relu_after_last_conv``.
    :meth:`__call__` maps an uploaded image to its last layer's features.
    The layers' maps come from a pool kept between calls (a fresh buffer's
    first write costs page mapping on CPU devices: one KITTI band's stack
    ~1.3 -> 0.9 s with reuse); callers hand the output back with :meth:`give`,
    :meth:`release_buffers` frees the pool.

    ``local_tiles``: the GEMM kernel (module docstring): None the profile's
    rule, False ``network_conv``, True ``network_conv_wg`` with the
    profile's tile (shrunk to fit), a dict ``network_conv_wg`` with those
    sizes (keys TM, TN, TK, RM, RN; not shrunk).  ``path`` says which
    ("local" or "register"); each layer's kernel and tile: ``layers[i][0]``.
    ``winograd``: on the register path, the 3 x 3 layers whose input channels
    are a multiple of RN by F(2x2, 3x3) with register block (RT, XA): None
    the profile's rule (:meth:`~mccnn_cl.opencl.device.DeviceProfile.winograd`),
    False never, a pair that block; a layer whose work-group does not fit the
    device stays direct.  ``layers[i][0].wino`` says which layers run so.
    """

    def __init__(self, ctx, weights, rn: int, conv_rm: int, relu_after_last: bool | None = None,
                 local_tiles=None, winograd=None):
        if rn not in (1, 2, 4, 8, 16):
            raise InputError(f"tile RN must be 1, 2, 4, 8 or 16, got {rn}")
        if int(conv_rm) < 1:
            raise InputError(f"tile CONV_RM must be >= 1, got {conv_rm}")
        self.ctx, self.rn, self.conv_rm = ctx, int(rn), int(conv_rm)
        self.local_tile = ctx.profile.local_tile("network_local_tiles", "network_gemm_tile", local_tiles)
        if self.local_tile is not None:
            check_tile(self.local_tile[0], CONV_BLOCKS, "conv GEMM")
        self.path = "register" if self.local_tile is None else "local"
        if winograd is None:
            winograd = ctx.profile.winograd()
        if winograd:
            rt, xa = (int(v) for v in winograd)
            if rt < 1 or xa not in (1, 2, 4, 8, 16):
                raise InputError(f"Winograd block (RT, XA) needs RT >= 1 and XA 1, 2, 4, 8 or 16, got {winograd}")
            winograd = (rt, xa)
        self.winograd = winograd if winograd and self.path == "register" else None
        relu_last = weights.relu_after_last_conv if relu_after_last is None else bool(relu_after_last)
        self.relu_after_last = relu_last
        self.layers = []  # (kernel, d_w, d_b, kernel size, padded outputs)
        cs = weights.input_channels  # the image is uploaded with C channels, stride C
        n = len(weights.conv)
        for i, (W, b) in enumerate(weights.conv):
            cout, cin, ks, _ = W.shape
            npad = round_up(cout, self.rn)
            wt = np.zeros((ks * ks * cin, npad), np.float32)
            wt[:, :cout] = W.transpose(2, 3, 1, 0).reshape(ks * ks * cin, cout)
            bp = np.zeros(npad, np.float32)
            bp[:cout] = b
            relu = int(i < n - 1 or relu_last)
            kern = self._winograd_kernel(ks, cin, cs, npad, relu)
            if kern is None:
                kern = self.kernel(ks, cin, cs, npad, relu)
            else:
                wt = winograd_weights(W, npad)
            self.layers.append((kern, ctx.to_device(wt), ctx.to_device(bp), ks, npad))
            cs = npad
        self.stride = cs            # channels per pixel of the output (maps padded)
        self.maps = weights.feature_maps
        self.patch = weights.patch_size
        self.widest = max(l[4] for l in self.layers)
        self._pool = BufferPool(ctx)

    def give(self, buf) -> None:
        """Return a map made by :meth:`__call__` for reuse."""
        self._pool.give(buf)

    def release_buffers(self) -> None:
        self._pool.clear()

    def _winograd_kernel(self, ks, cin, cs, npad, relu):
        """The layer's network_conv_wino kernel, or None where the layer runs direct
        (no Winograd block, not 3 x 3, input channels not a multiple of RN, or a
        work-group that does not fit the device's local memory or the kernel)."""
        if self.winograd is None or ks != 3 or cin % self.rn:
            return None
        rt, xa = self.winograd
        if winograd_local_bytes(cin, npad, self.rn, rt) > self.ctx.local_mem:
            return None
        kern = self.ctx.kernel(CONV_WINO_CL, "network_conv_wino", CIN=cin, CS=cs, NP=npad, RN=self.rn,
                               RELU=int(relu), RT=rt, XA=xa)
        if npad // self.rn > self.ctx.work_group_size(kern):
            return None
        return ConvKernel(kern, None, (rt, xa))

    def kernel(self, ks, cin, cs, npad, relu) -> ConvKernel:
        """The GEMM kernel of one layer (KS x KS, CIN channels read at stride
        CS, NP padded outputs) on this stack's path."""
        defs = dict(KS=ks, CIN=cin, CS=cs, NP=npad, RELU=int(relu))
        if self.local_tile is None:
            return ConvKernel(self.ctx.kernel(CONV_CL, "network_conv", RM=self.conv_rm, RN=self.rn, **defs), None)
        sizes, forced = self.local_tile
        sizes = dict(sizes)
        if not forced:  # no wider than the layer: TN up to NP, TK up to the K terms
            sizes["TN"] = min(sizes["TN"], round_up(npad, sizes["RN"]))
            sizes["TK"] = min(sizes["TK"], ks * ks * cin)

        kern, tile = fit_tile(
            self.ctx, f"conv GEMM (KS={ks}, CIN={cin}, NP={npad})", sizes, forced,
            lambda t: 4 * t["TK"] * (t["TM"] + t["TN"]) + 8 * t["TM"],
            lambda t: (t["TN"] // t["RN"], t["TM"] // t["RM"]),
            lambda t: self.ctx.kernel(CONV_WG_CL, "network_conv_wg", **defs, **t),
            shrinker(*CONV_BLOCKS))  # fewer pixels, then fewer channels, then a thinner slice
        return ConvKernel(kern, tile)

    def launch(self, conv: ConvKernel, d_in, w_in, d_w, d_b, d_out, w_out, m_total, npad, row0: int = 0):
        """Enqueue one layer; ``row0``: the map's first row in the whole map it was cut
        from (a Winograd layer's tile grid is anchored at that map's row 0)."""
        kern, tile, wino = conv
        if wino is not None:
            launch_winograd(self.ctx, kern, wino[0], self.rn, d_in, w_in, d_w, d_b, d_out, w_out, m_total // w_out,
                            npad, row0)
            return
        if tile is None:
            # a work-group spans every channel group (a fixed count per layer)
            gsize, lsize = launch_sizes(self.ctx, (npad // self.rn, math.ceil(m_total / self.conv_rm)))
            if lsize is not None:
                lsize = (npad // self.rn, CONV_ROWS_LOCAL)
                gsize = (lsize[0], round_up(gsize[1], CONV_ROWS_LOCAL))
        else:
            wn, wm = tile["TN"] // tile["RN"], tile["TM"] // tile["RM"]
            lsize = (wn, wm)
            gsize = (math.ceil(npad / tile["TN"]) * wn, math.ceil(m_total / tile["TM"]) * wm)
        kern(self.ctx.queue, gsize, lsize, d_in, np.int32(w_in), d_w, d_b, d_out,
             np.int32(w_out), np.int32(m_total))

    def __call__(self, d_img, H: int, W: int, row0: int = 0):
        """All conv layers over an uploaded image ``[H][W][C]`` (float32);
        ``row0``: its first row in the whole image it was cut from (a band,
        a row tile: the Winograd layers then give the whole image's values).

        Returns a device buffer ``[(H-P+1) * (W-P+1)][stride]`` (hand it
        back with :meth:`give`); buffers may be larger than the map."""
        ctx = self.ctx
        d_in, h, w = d_img, int(H), int(W)
        for kern, d_w, d_b, ks, npad in self.layers:
            ho, wo = h - ks + 1, w - ks + 1
            d_out = self._pool.take(ho * wo * npad * 4, "network feature map")
            self.launch(kern, d_in, w, d_w, d_b, d_out, wo, ho * wo, npad, row0)
            if d_in is not d_img:
                self._pool.give(d_in)  # the in-order queue runs its next writer after this layer
            d_in, h, w = d_out, ho, wo
        return d_in

    def run_image(self, band: np.ndarray, row0: int = 0):
        """Upload a standardised float32 image (rows x W x C; its first row is row
        ``row0`` of the whole image) and run the stack."""
        H, W = band.shape[:2]
        d_img = self.ctx.to_device(np.ascontiguousarray(band, dtype=np.float32))
        d_feat = self(d_img, H, W, row0)
        d_img.release()
        return d_feat

    def scratch_bytes(self, rows: int, w: int) -> int:
        """Bytes of two maps of the widest layer over ``rows`` feature rows of width ``w``
        (input and output of one convolution, image margins included)."""
        return 2 * (rows + self.patch) * (w + self.patch - 1) * self.widest * 4

    def flops(self, height: int, width: int, weights) -> tuple:
        """(FLOP of the stack on both images, feature height, feature width)."""
        hh, ww, total = int(height), int(width), 0
        for W, _ in weights.conv:
            cout, cin, ks, _ = W.shape
            hh, ww = hh - ks + 1, ww - ks + 1
            total += 2 * 2 * hh * ww * ks * ks * cin * cout
        return total, hh, ww


class ConvNetCost(MatchingCost):
    """A network cost's common state and its banded volume: the weights
    checked against ``architecture``, volume storage (float16 with ``half``),
    patch, margin, channels, the tiles (the profile's, updated by ``tiles``)
    and the conv stack (:class:`ConvStack`, its GEMM path by ``local_tiles``).
    Subclasses implement ``band_rows(h, w)`` and ``_enqueue(L, R, D, h, w,
    rows, d_cost, progress, host=None)``; ``label`` names the cost in an
    OpenCL error."""

    local = False  # the volume is computed once for the whole image (host memory when tiled)
    label = "network cost"
    #: the conv stack's channels per work-item: the head's RN (the fc networks, whose L4 split and
    #: hidden width are padded to it) or the tiles' own CONV_RN (fst: the stack alone)
    stack_rn_from_head = False

    def __init__(self, ctx, weights, tiles=None, half: bool = False, local_tiles=None, winograd=None):
        weights.validate()
        if weights.architecture != self.architecture:
            raise WeightsError(f"{type(self).__name__} runs {self.architecture} networks, "
                               f"these weights are {weights.architecture}")
        self.ctx = ctx
        self.weights = weights
        self.half = bool(half)
        self.vdtype = np.dtype(np.float16 if half else np.float32)  # volume storage (kernels/common.h)
        self.patch = weights.patch_size
        self.margin = weights.margin
        self.channels = weights.input_channels
        self.tiles = default_tiles(ctx)
        self.tiles.update(tiles or {})
        given = tiles or {}
        if self.stack_rn_from_head or ("RN" in given and "CONV_RN" not in given):
            rn = self.tiles["RN"]  # an explicit RN sets both, as it did before CONV_RN
        else:
            rn = self.tiles["CONV_RN"]
        self.stack = ConvStack(ctx, weights, int(rn), int(self.tiles["CONV_RM"]), local_tiles=local_tiles,
                               winograd=winograd)

    def band_rows(self, h: int, w: int) -> int:
        raise NotImplementedError

    def rows_of(self, h: int, w: int, rows=None) -> int:
        """Volume rows per band of an h x w volume: :meth:`band_rows` (the most a band
        may take), or ``rows`` when given (at least 1, at most :meth:`band_rows`:
        the stereo method's planner picks fewer under a tight ``memory_limit``)."""
        most = self.band_rows(h, w)
        if rows is None:
            return most
        if isinstance(rows, (bool, np.bool_)) or not isinstance(rows, (int, np.integer)) or rows < 1:
            raise InputError(f"band rows must be an integer >= 1, not {rows!r}")
        return min(int(rows), most)

    def _enqueue(self, L, R, D, h, w, rows, d_cost, progress, host=None, stats=None, row0=0):
        raise NotImplementedError

    @staticmethod
    def standardised(L, R, stats=None):
        """The images as the network sees them (:func:`normalise`): each by its own
        mean and std, or by ``stats`` (``((mean, std), (mean, std))``: e.g. those of
        the whole image a padded image or a row tile was cut from, so that its
        values equal the whole image's, bit for bit)."""
        if stats is None:
            return normalise(L), normalise(R)
        return normalise(L, stats[0]), normalise(R, stats[1])

    def _pools(self) -> list:
        """The pools the cost's scratch comes from (a lent buffer is carved through them)."""
        return [self.stack._pool]

    def _pooled_scratch(self, h: int, w: int, rows=None) -> list:
        """Upper bounds of the buffers the pools hold at once for an h x w
        volume in bands of ``rows`` rows (what a lent buffer can hold): the
        conv stack's two maps."""
        one = self.stack.scratch_bytes(self.rows_of(h, w, rows), w) // 2
        return [one, one]

    def lent_scratch_bytes(self, h: int, w: int, lent: int, rows=None) -> int:
        """Of :meth:`scratch_bytes`, the bytes surely carved from a lent buffer of
        ``lent`` bytes: all the pools' buffers when they fit, else at least
        the arena's size less its largest buffer and the alignment gaps (a
        buffer is made afresh only when it does not fit behind those carved
        before it)."""
        if not self.ctx.sub_buffers:
            return 0
        items = self._pooled_scratch(h, w, rows)
        sure = int(lent) - max(items) - len(items) * self.ctx.sub_buffer_align
        return max(0, min(sum(items), sure))

    def __call__(self, left, right, max_disparity, out=None, progress=None, stats=None, scratch=None, rows=None,
                 row0=0):
        """Inputs checked, the volume's buffer (``out`` or a new one), :meth:`_enqueue`
        over bands of :meth:`rows_of` rows (``rows``; None: :meth:`band_rows`);
        ``stats``: ``((mean, std) of the left, (mean, std)
        of the right)`` to standardise with instead of the images' own
        (:func:`mccnn_cl.imageops.standardise`; None: their own).  ``scratch``: a
        device buffer (not ``out``) lent for this call: the conv maps (and fst's
        planar features) that no kept buffer holds are carved from it
        (:class:`~mccnn_cl.opencl.context.Arena`); its contents are overwritten, and
        it is the caller's again when the call returns (later commands of the
        in-order queue run after the cost's)."""
        if scratch is None or not self.ctx.sub_buffers:
            return self._call(left, right, max_disparity, out, progress, stats, rows, row0)
        if scratch is out:
            raise InputError("the lent scratch buffer must not be the volume's buffer")
        arena = Arena(self.ctx, scratch)
        pools = self._pools()
        for pool in pools:
            pool.lend(arena)
        done = False
        try:
            volume = self._call(left, right, max_disparity, out, progress, stats, rows, row0)
            done = True
            return volume
        finally:  # after an error (Ctrl-C too) the maps still taken are released, not reported
            for pool in pools:
                pool.end_loan(check=done)

    def _call(self, left, right, max_disparity, out, progress, stats, rows=None, row0=0):
        ctx = self.ctx
        L, R, D, h, w = check_cost_inputs(left, right, max_disparity, self.channels, self.patch)
        nbytes = D * h * w * self.vdtype.itemsize
        ctx.check_alloc(nbytes, f"cost volume ({D} x {h} x {w})")
        rows = self.rows_of(h, w, rows)
        if out is None:
            out = ctx.empty(nbytes, "cost volume")
        elif out.size < nbytes:
            raise InputError(f"out buffer has {out.size} bytes, the volume needs {nbytes}")
        try:
            self._enqueue(L, R, D, h, w, rows, out, progress, stats=stats, row0=row0)
        except ctx.cl.Error as exc:
            raise OpenCLError(f"{self.label} ({D} x {h} x {w}) failed on {ctx.describe()}: {exc}") from exc
        return out

    def to_host(self, left, right, max_disparity, max_bytes=None, progress=None, stats=None, rows=None, row0=0):
        """Each band (at most ``rows`` rows, :meth:`rows_of`) computed into one
        device buffer of at most ``max_bytes`` (default: the max allocation)
        and copied into the host volume
        (``_enqueue(..., host=)``); values identical to :meth:`__call__`'s.
        ``stats``: as :meth:`standardised` (a row tile standardised with the whole
        image's stats gives those rows of the whole image's volume;
        :mod:`mccnn_cl.distributed`)."""
        ctx = self.ctx
        L, R, D, h, w = check_cost_inputs(left, right, max_disparity, self.channels, self.patch)
        row = D * w * self.vdtype.itemsize
        limit = ctx.max_alloc if max_bytes is None else min(int(max_bytes), ctx.max_alloc)
        if row > limit:
            raise InputError(f"one row of the cost volume ({D} x {w} {self.vdtype.name}, {row / 2**20:.1f} MiB) "
                             f"does not fit in {limit / 2**20:.1f} MiB of device memory; reduce the "
                             "disparity range or the image width")
        rows = min(self.rows_of(h, w, rows), limit // row)
        host = np.empty((D, h, w), self.vdtype)
        d_band = ctx.empty(D * rows * w * self.vdtype.itemsize, "cost volume band")
        try:
            self._enqueue(L, R, D, h, w, rows, d_band, progress, host=host, stats=stats, row0=row0)
        except ctx.cl.Error as exc:
            raise OpenCLError(f"{self.label} ({D} x {h} x {w}, in bands of {rows} rows) failed on "
                              f"{ctx.describe()}: {exc}") from exc
        finally:
            d_band.release()
        return host
