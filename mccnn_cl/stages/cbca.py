"""Cross-based cost aggregation, CBCA (paper, "Cross-based cost aggregation") - drives ``kernels/cbca.cl``.

    U_d(p) = {q | q in U^L(p), qd in U^R(pd)},   C^0 = C,   C^i(p, d) = mean of C^{i-1}(q, d) over U_d(p)

U(p) is the union of the horizontal arms of the pixels on p's vertical arm
(arms: :class:`mccnn_cl.stages.cross.CrossArms`).  From the set definition,
U_d(p) takes the rows y - min(u_L(x,y), u_R(x-d,y)) .. y + min(w_L, w_R) and in
row y' the columns x - min(l_L(x,y'), l_R(x-d,y')) .. x + min(r_L, r_R) (the
released code's "min of both arms"), so a mean is a column sum of row sums
("orthogonal integral images"): pass 1 sums rows, pass 2 columns and divides.
Intervals are clamped by index to the valid cells [d, W-1], so NaN never
enters a sum; p is always in U_d(p).

Five kernel paths compute these two passes (:meth:`DeviceProfile.cbca_path
<mccnn_cl.opencl.device.DeviceProfile.cbca_path>` picks one from ``max_arm``, the
bound of the arm lengths compiled in, and the device): "running" (``cbca_rows``
/ ``cbca_columns``, any arm length: compensated running prefix sums),
"short" (``*_short``, max_arm <= SHORT_MAX: direct masked sums on float16
lanes), "fused" (``cbca_fused_short``: both passes in one launch, one
work-item walking each disparity plane, a ring of row sums in scratch),
"multi" (``cbca_fused_multi_short``: up to MULTI_K iterations per launch, the
volume read and written once) and "workgroup" (below).  All work in place;
the fused paths are bit-identical to the short passes, all agree with the
float64 reference.  Scratch: :meth:`CBCA.scratch_bytes`.  Measurements:
BENCHMARKS.md, "History".

The "workgroup" path (``kernels/cbca_wg.cl``, max_arm <= SHORT_MAX; the
default on the profile's ``gpu`` column, rule ``cbca_workgroup``) is the
short path laid out for GPUs, where the others run one work-item per line
or per plane: ``cbca_rows_wg`` runs one work-group per (row, disparity) with
its L work-items over L consecutive columns at a time, ``cbca_columns_wg``
one work-group per (tile of TX columns, disparity) with TX x TY work-items
over TY rows at a time (H x D and ceil(W / TX) x D groups: ~84 000 and
~9 000 at KITTI size).  A work-group owns its line, so both passes stay in
place: the original values a chunk's windows need wait in a ring in local
memory (L + 2 max_arm floats; (TY + 2 max_arm) x TX row sums and byte row
counts) until the group has read them, two barriers per chunk.  The float
operations per cell are those of the short passes in the same order, so the
results equal the short path bit for bit (float32 and half storage), and
the fused paths in float32.  Work-group sizes (:meth:`CBCA.work_group_sizes`):
L the kernel's preferred multiple times enough to cover the row, at most
256; TX the columns kernel's preferred multiple (a warp, a wavefront), TY
filling 256 work-items; each within the kernel's CL_KERNEL_WORK_GROUP_SIZE,
the device's item sizes and local memory.  ``local_size=`` forces them (the
tests run 1 up to the kernel maximum on PoCL and Oclgrind).  Longer arms
(max_arm > SHORT_MAX) fall back to the running sums, as on every device.
No scratch.
"""

from __future__ import annotations

import numpy as np

from ..opencl.context import launch, round_up
from ..errors import InputError
from .cross import ARM_LIMIT, check_size
from .cross import max_arm as arm_bound
from .disparity import volume_bytes

#: Largest max_arm served by the short-arm kernels (CBCA_SHORT_MAX in cbca.cl).
SHORT_MAX = 8
_VW = 16  # float16 lanes
_GROUPS = 8  # 16-column groups per work-item of cbca_columns_short (CBCA_GROUPS)
#: Iterations per launch of cbca_fused_multi_short (CBCA_K; its scratch grows with it).
MULTI_K = 4
#: Work-items per group the "workgroup" path aims at by default (both kernels).
WG_TARGET = 256


class CBCA:
    """C^iterations_CBCA of a float32 [D][H][W] cost volume; see the module docstring.

    ``max_arm`` (``__call__`` argument, default 255, right for any arms): an
    upper bound of every arm length in the arm buffers; a program is built
    per value.  PASS THE TIGHT BOUND ``mccnn_cl.stages.cross.max_arm(eta,
    include_neighbor)`` (3 for the paper's eta = 4): it selects the fast
    short-arm kernels.  Arms longer than ``max_arm`` are truncated to it.
    ``short=False`` forces the running-sum path, ``fused=False`` the two short
    passes, ``multi=False`` the one-iteration fused kernel (for comparisons);
    ``workgroup=True`` the GPU-shaped passes (it takes precedence over the
    fused rule; ``workgroup=False`` excludes them); None: the device's rule
    (:meth:`mccnn_cl.opencl.device.DeviceProfile.cbca_path`; the work-group rule
    applies only when neither ``fused`` nor ``multi`` is given).
    ``local_size``: the "workgroup" path's work-group sizes, an int L (rows
    groups of L, column groups :meth:`columns_shape` of L) or a pair
    ``(L, (TX, TY))``; default :meth:`work_group_sizes`.
    ``half=True``: volumes stored as half (``VOL_HALF``, kernels/common.h);
    sums stay float (the two-pass kernels store their row sums in the volume,
    so they round them to half too).  ``__init__``'s ``max_arm`` only
    pre-builds that program.  ``select_add``: the "multi" path's form of a
    masked term (``CBCA_SELECT_ADD`` in kernels/cbca.cl; the same bits either
    way); None: 1 where the CPU has no AVX-512
    (:attr:`~mccnn_cl.opencl.device.DeviceProfile.wide_vectors`).
    """

    #: Extra D x H x W volumes a call needs beyond ``d_cost`` and ``out``
    #: (for the memory planner): none, on every path, also when out is d_cost.
    scratch_volumes = 0

    def __init__(self, ctx, max_arm: int = ARM_LIMIT, short: bool = True, fused: bool | None = None,
                 half: bool = False, multi: bool | None = None, workgroup: bool | None = None,
                 local_size=None, select_add: bool | None = None):
        self.ctx = ctx
        self.select_add = select_add  # multi path's masked-term form (None: by the device; tests force both)
        self.short = bool(short)
        rule = ctx.profile.rule
        if workgroup and fused:
            raise InputError("CBCA: workgroup=True and fused=True exclude each other")
        self.workgroup = bool((rule("cbca_workgroup") and fused is None and multi is None)
                              if workgroup is None else workgroup)
        self.fused = bool(rule("cbca_fused") if fused is None else fused)
        self.multi = bool(rule("cbca_multi") if multi is None else multi)
        self.half = bool(half)
        self.local_size = _check_local_size(local_size)
        self._wg_sizes = {}  # (W, max_arm, local_size, local memory) -> work_group_sizes
        self._kernels = {}
        self._ring = None  # (nbytes, row-sum ring, count ring) of cbca_fused_short
        self._multi = None  # (sizes, [float, byte, row scratch]) of cbca_fused_multi_short
        self._get(max_arm)

    def path(self, max_arm) -> str:
        """The kernel path for arms of at most ``max_arm``: "workgroup", "multi", "fused", "short" or "running"."""
        return self.ctx.profile.cbca_path(int(max_arm), SHORT_MAX, self.short, self.fused, self.multi,
                                          self.workgroup)

    def scratch_bytes(self, D, W, params) -> int:
        """Device bytes of the scratch a call with ``params`` (the
        Hyperparameters: their arms bound ``max_arm(cbca_eta,
        cross_include_neighbor)``) allocates and keeps: :func:`path_scratch_bytes`."""
        arm = arm_bound(params.cbca_eta, params.cross_include_neighbor)
        return path_scratch_bytes(D, W, arm, self.path(arm))

    def _get(self, max_arm):
        max_arm = int(max_arm)
        if not 0 <= max_arm <= ARM_LIMIT:
            raise InputError(f"max_arm must be in [0, {ARM_LIMIT}], got {max_arm}")
        path = self.path(max_arm)
        k = self._kernels.get((max_arm, path))
        if k is None:
            ctx, half = self.ctx, int(self.half)
            if path == "multi":
                # the masked terms' form (kernels/cbca.cl, CBCA_MASKED_SUM): one masked add where the CPU
                # has AVX-512, the mask on the term off the chain of adds elsewhere (the same bits);
                # CBCA_CPU_ASM: asm barriers where the kernel is compiled straight to x86 (PoCL)
                sel = int(self.select_add if self.select_add is not None else not ctx.profile.wide_vectors)
                kern = ctx.kernel("cbca.cl", "cbca_fused_multi_short", MAX_ARM=max_arm, CBCA_K=MULTI_K, VOL_HALF=half,
                                  CBCA_SELECT_ADD=sel, CBCA_CPU_ASM=int(ctx.profile.is_cpu), CBCA_PART=2)
                # a work-item walks a whole plane: on CPUs groups of one spread the D planes evenly over the cores
                k = [(kern, ctx.profile.line_group(ctx, kern, ctx.profile.rule("cbca_multi_group_of_one")))]
            elif path == "workgroup":
                defs = dict(MAX_ARM=max_arm, VOL_HALF=half)
                k = [(ctx.kernel("cbca_wg.cl", "cbca_rows_wg", **defs), None),
                     (ctx.kernel("cbca_wg.cl", "cbca_columns_wg", **defs), None)]
            elif path == "fused":
                # CBCA_PART 1: the program without the multi kernel (a binary holds code for every
                # kernel of its program, and PoCL compiles them all to hand it out)
                kern = ctx.kernel("cbca.cl", "cbca_fused_short", MAX_ARM=max_arm, CBCA_GROUPS=_GROUPS, VOL_HALF=half,
                                  CBCA_PART=1)
                k = [(kern, ctx.profile.line_group(ctx, kern))]
            else:
                suffix = "_short" if path == "short" else ""
                defs = dict(MAX_ARM=max_arm, CBCA_GROUPS=_GROUPS) if path == "short" else dict(MAX_ARM=max_arm)
                defs["VOL_HALF"] = half
                defs["CBCA_PART"] = 1
                k = [(kern, ctx.profile.line_group(ctx, kern))
                     for kern in (ctx.kernel("cbca.cl", "cbca_rows" + suffix, **defs),
                                  ctx.kernel("cbca.cl", "cbca_columns" + suffix, **defs))]
            k = (k, path)
            self._kernels[(max_arm, path)] = k
        return k

    def release_buffers(self) -> None:
        """Free the scratch kept between calls (the "fused" path's rings, the
        "multi" path's buffers: :meth:`scratch_bytes`); the next call makes it
        again.  Work already queued on them still runs (OpenCL keeps a released
        buffer until its commands complete)."""
        for kept in (self._ring[1:] if self._ring else ()), (self._multi[1] if self._multi else ()):
            for buf in kept:
                buf.release()
        self._ring = None
        self._multi = None

    def _rings(self, D, W, max_arm):
        """The fused path's scratch rings (kept and reused while large enough)."""
        nbytes = path_scratch_bytes(D, W, max_arm, "fused")
        if self._ring is None or self._ring[0] < nbytes:
            self._ring = None
            ring = self.ctx.empty(4 * nbytes // 5, "CBCA row-sum ring")
            cring = self.ctx.empty(nbytes // 5, "CBCA count ring")
            self._ring = (nbytes, ring, cring)
        return self._ring[1], self._ring[2]

    def _multi_scratch(self, D, W, max_arm):
        """cbca_fused_multi_short's scratch buffers (kept and reused while large enough)."""
        sizes = _multi_scratch(D, W, max_arm)
        if self._multi is None or any(a < b for a, b in zip(self._multi[0], sizes)):
            self._multi = None
            self._multi = (sizes, [self.ctx.empty(n, f"CBCA multi scratch {i}") for i, n in enumerate(sizes)])
        return self._multi[1]

    def __call__(self, d_cost, d_arms_left, d_arms_right, D, H, W, iterations=4, max_arm=ARM_LIMIT,
                 out=None):
        """Enqueue ``iterations`` CBCA passes over ``d_cost`` (D x H x W float32,
        NaN where invalid).  Returns ``out`` (allocated when None; may be
        ``d_cost`` itself to aggregate in place).  ``d_cost`` is left untouched
        unless it is ``out``."""
        H, W = check_size(H, W, "cost volume")
        D, iterations = int(D), int(iterations)
        if D < 1:
            raise InputError(f"the cost volume needs at least one disparity level, got D = {D}")
        if iterations < 0:
            raise InputError(f"iterations must be >= 0, got {iterations}")
        nbytes = volume_bytes(self.half) * D * H * W
        if out is None:
            out = self.ctx.empty(nbytes, "CBCA output volume")
        kerns, path = self._get(max_arm)
        if iterations == 0:
            if out is not d_cost:
                self.ctx.cl.enqueue_copy(self.ctx.queue, out, d_cost, byte_count=nbytes)
            return out
        dims = (np.int32(D), np.int32(H), np.int32(W))
        src = d_cost
        if path == "workgroup":
            (k_rows, _), (k_cols, _) = kerns
            L, (TX, TY) = self.work_group_sizes(W, max_arm)
            cl, A = self.ctx.cl, int(max_arm)
            ring = cl.LocalMemory(4 * (L + 2 * A))
            rsum, rcnt = cl.LocalMemory(4 * (TY + 2 * A) * TX), cl.LocalMemory((TY + 2 * A) * TX)
            for _ in range(iterations):
                launch(self.ctx, "CBCA rows (work-groups)", k_rows, (L, H, D),
                       src, out, d_arms_left, d_arms_right, ring, *dims, local_size=(L, 1, 1))
                launch(self.ctx, "CBCA columns (work-groups)", k_cols, (round_up(W, TX), TY, D),
                       out, d_arms_left, d_arms_right, rsum, rcnt, *dims, local_size=(TX, TY, 1))
                src = out
            return out
        if path == "multi":
            (k_multi, l_multi), = kerns
            scratch = self._multi_scratch(D, W, max_arm)
            done = 0
            while done < iterations:
                n = min(MULTI_K, iterations - done)
                launch(self.ctx, "CBCA", k_multi, (round_up(D, l_multi),),
                       src, out, *scratch, d_arms_left, d_arms_right, *dims, np.int32(n), local_size=(l_multi,))
                src = out
                done += n
            return out
        if path == "fused":
            (k_fused, l_fused), = kerns
            ring, cring = self._rings(D, W, max_arm)
            for _ in range(iterations):
                launch(self.ctx, "CBCA", k_fused, (round_up(D, l_fused),),
                       src, out, ring, cring, d_arms_left, d_arms_right, *dims, local_size=(l_fused,))
                src = out
            return out
        (k_rows, l_rows), (k_cols, l_cols) = kerns
        for _ in range(iterations):
            launch(self.ctx, "CBCA rows", k_rows, (round_up(H, l_rows), D),
                   src, out, d_arms_left, d_arms_right, *dims, local_size=(l_rows, 1))
            ncol = -(-W // (_VW * _GROUPS)) if path == "short" else W
            launch(self.ctx, "CBCA columns", k_cols, (round_up(ncol, l_cols), D),
                   out, d_arms_left, d_arms_right, *dims, local_size=(l_cols, 1))
            src = out
        return out


    # -- the "workgroup" path's work-group sizes ------------------------------
    def _limits(self, kern, dim):
        """(preferred multiple, largest size) of ``kern`` along local dimension ``dim``."""
        cl, dev = self.ctx.cl, self.ctx.device
        pref = int(kern.get_work_group_info(cl.kernel_work_group_info.PREFERRED_WORK_GROUP_SIZE_MULTIPLE, dev))
        return max(1, pref), min(self.ctx.work_group_size(kern), int(dev.max_work_item_sizes[dim]))

    def columns_shape(self, L, max_arm=SHORT_MAX):
        """(TX, TY) of the columns kernel for groups of about ``L`` work-items:
        TX the kernel's preferred multiple (coalesced rows of a warp or
        wavefront; L if smaller), TY = L // TX."""
        kern = self._get(max_arm)[0][1][0]
        pref, _ = self._limits(kern, 0)
        TX = max(1, min(int(L), pref))
        return TX, max(1, int(L) // TX)

    def work_group_sizes(self, W, max_arm):
        """(L, (TX, TY)): the rows kernel's groups of L, the columns kernel's of
        TX x TY (module docstring), forced ones checked against the kernels'
        limits (InputError)."""
        key = (int(W), int(max_arm), self.local_size, self.ctx.local_mem)
        sizes = self._wg_sizes.get(key)
        if sizes is None:
            sizes = self._wg_sizes[key] = self._work_group_sizes(int(W), int(max_arm))
        return sizes

    def _work_group_sizes(self, W, A):
        (k_rows, _), (k_cols, _) = self._get(A)[0]
        pref_r, max_r = self._limits(k_rows, 0)
        pref_c, max_c = self._limits(k_cols, 0)
        _, max_cy = self._limits(k_cols, 1)
        local = self.ctx.local_mem

        def rows_bytes(L):  # the rows kernel's ring
            return 4 * (L + 2 * A)

        def cols_bytes(tx, ty):  # the columns kernel's rings: float row sums, byte counts
            return 5 * (ty + 2 * A) * tx

        if self.local_size is None:
            L = max(1, min(max_r, WG_TARGET, round_up(W, pref_r)))
            TX = max(1, min(pref_c, max_c))
            TY = max(1, min(max_cy, max_c // TX, WG_TARGET // TX))
            while L > 1 and rows_bytes(L) > local:
                L //= 2
            while TY > 1 and cols_bytes(TX, TY) > local:
                TY //= 2
            while TX > 1 and cols_bytes(TX, TY) > local:
                TX //= 2
        else:
            L, shape = self.local_size
            TX, TY = self.columns_shape(L, A) if shape is None else shape
            where = self.ctx.describe()
            if L > max_r:
                raise InputError(f"CBCA rows work-group {L} exceeds the kernel's maximum {max_r} on {where}")
            if TX * TY > self.ctx.work_group_size(k_cols) or TX > max_c or TY > max_cy:
                raise InputError(f"CBCA columns work-group {TX} x {TY} exceeds the kernel's limits on {where}")
        for what, n in (("rows", rows_bytes(L)), ("columns", cols_bytes(TX, TY))):
            if n > local:
                raise InputError(f"CBCA {what} work-groups ({L}; {TX} x {TY}) need {n} bytes of local memory, "
                                 f"more than the {local} of {self.ctx.describe()}")
        return L, (TX, TY)


def _check_local_size(local_size):
    """``local_size`` as (L, (TX, TY) or None), or None."""
    if local_size is None:
        return None
    if isinstance(local_size, (int, np.integer)):
        L, shape = int(local_size), None
    else:
        L, shape = local_size
        L, shape = int(L), tuple(int(v) for v in shape)
        if len(shape) != 2 or min(shape) < 1:
            raise InputError(f"CBCA columns work-group shape must be (TX, TY) >= 1, got {local_size}")
    if L < 1:
        raise InputError(f"CBCA work-group size must be >= 1, got {local_size}")
    return L, shape


def path_scratch_bytes(D, W, max_arm, path) -> int:
    """Scratch a path keeps: "fused": rings of D x (2 max_arm + 1) x W float32
    row sums and as many byte counts (9.8 MB for D = 228, W = 1232, max_arm =
    3); "multi": :func:`_multi_scratch` (58.8 MB there, 14.3 % of a
    228 x 367 x 1232 float32 volume); 0 on the two-pass paths ("running",
    "short", "workgroup": local memory only)."""
    if path == "multi":
        return sum(_multi_scratch(D, W, max_arm))
    if path == "fused":
        return 5 * int(D) * (2 * int(max_arm) + 1) * int(W)
    return 0


def _multi_scratch(D, W, max_arm, k=MULTI_K):
    """Bytes of cbca_fused_multi_short's three scratch buffers (kernels/cbca.cl):
    per plane, with WR = W rounded up to 16 and A = max_arm,
    k (2A + 1) float rows (row sums) + (k - 1) A + 1 ushort rows (counts),
    5 (max(k, 2) A + 1) byte rows (arms, row counts) and three rows of WR + 32 cells (float32
    size, an upper bound for half volumes)."""
    D, A = int(D), int(max_arm)
    WR = -(-int(W) // _VW) * _VW
    nf = k * (2 * A + 1) + ((k - 1) * A + 2) // 2  # row sums; counts as ushort, 2 rows per float row
    nb = 5 * (max(k, 2) * A + 1)
    return (4 * D * nf * WR, D * nb * WR, 4 * D * 3 * (WR + 2 * _VW))
