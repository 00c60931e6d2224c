"""Cross-based cost aggregation, CBCA (paper, "Cross-based cost aggregation")
- drives ``kernels/cbca.cl`` (``cbca_fused_multi_short``, ``cbca_fused_short``,
``cbca_rows[_short]``, ``cbca_columns[_short]``).

Definition (paper)::

    U_d(p) = {q | q in U^L(p), qd in U^R(pd)},   qd = q - (d, 0), pd = p - (d, 0)
    C^0 = C,   C^i(p, d) = mean of C^{i-1}(q, d) over q in U_d(p),   i = 1..4

where U(p) is the union of the horizontal arms of all pixels on p's vertical
arm.  Arms come from :class:`mccnn_cl.stages.cross.CrossArms` (byte planes
[4][H][W]: left l, right r, up u, down w).

Derivation of the two passes.  Write p = (x, y).  p's vertical arm is the
column segment {(x, y') : y - u(x, y) <= y' <= y + w(x, y)}, one pixel per
row, so U(p) meets row y' exactly in the horizontal arm of (x, y'):

    U^L(p) ∩ row y' = [x - l_L(x, y'), x + r_L(x, y')]      if y' in p's vertical arm (left image)
    U^R(pd) ∩ row y' = [x-d - l_R(x-d, y'), x-d + r_R(x-d, y')]  if y' in pd's vertical arm (right image)

q = (x', y') is in U_d(p) iff q is in U^L(p) and (x' - d, y') is in U^R(pd).
The second condition reads y' in pd's vertical arm and
x - l_R(x-d, y') <= x' <= x + r_R(x-d, y') (shift by +d).  Hence

    rows:     y' in [y - min(u_L(x,y), u_R(x-d,y)),  y + min(w_L(x,y), w_R(x-d,y))]
    in row y': x' in [x - min(l_L(x,y'), l_R(x-d,y')),  x + min(r_L(x,y'), r_R(x-d,y'))]

(the released code's "min of both images' arms", derived here from the set).
The row interval depends on (d, y', x) only, not on p's row, so
|U_d(p)| * C^i(p, d) = sum over the rows y' of S(d, y', x), where S is the
row sum over the row interval: "orthogonal integral images".  Pass 1
(rows) computes S for every cell, pass 2 (columns) sums S and the row counts
down the column and divides.

Validity: for a valid p (d <= x) every q of U_d(p) is valid, because the
right arm at x - d never leaves the right image: x' - d >= x - d - l_R >= 0.
The kernels also clamp every interval to the valid cells [d, W - 1] (and
rows to [0, H - 1]) by index, so an invalid (NaN) cell can never enter a sum
or a count; invalid output cells are NaN.  p itself is always in U_d(p), so
the count is >= 1.

Two implementations of the same two passes (``kernels/cbca.cl``), chosen by
``max_arm`` (an upper bound of the arm lengths, compiled in as MAX_ARM):

* ``cbca_rows`` / ``cbca_columns`` (any max_arm, the "running sums" of the
  issue): one work-item walks a row (resp. a column) with a running prefix
  sum and a look-ahead of MAX_ARM cells kept in a private ring; a window sum
  is P(b) - P(a - 1), so the work per cell does not grow with the arm
  length.  The prefix sums are compensated (TwoSum pairs), so a window sum is
  exact to a few ulp of the window's own magnitude, independent of the line
  length (plain float32 prefixes of a 1240-px row would lose ~1e-4 of the
  cost range).
* ``cbca_rows_short`` / ``cbca_columns_short`` (max_arm <= 8, used whenever
  it applies unless ``CBCA(ctx, short=False)``): direct sums of the
  2 max_arm + 1 candidate cells, masked by index, on float16 lanes along x.
  A column work-item covers 8 x 16 columns, so each row step reads 8
  consecutive lines, which the CPU's prefetcher follows.  The work per cell
  grows with max_arm, but for the paper's arms (<= 3 px) this is ~3x faster
  on PoCL than the scalar running sums, which cannot use the vector units.

* ``cbca_fused_short`` (max_arm <= 8, the default whenever the short-arm
  kernels apply; ``CBCA(ctx, fused=False)`` selects the two short passes):
  both short passes in one launch per iteration, so an iteration reads the
  volume once and writes it once instead of twice each.  One work-item per
  disparity plane walks down the rows: it forms row t's row sums (the same
  float16 masked sums as ``cbca_rows_short``) into a ring of the last
  2 max_arm + 1 rows in a small global scratch, then sums the ring rows of
  U_d(p) for row t - max_arm (as ``cbca_columns_short``) and writes it.  Same
  float operations in the same order: bit-identical to the two passes.  On
  PoCL (2 cores, KITTI-size volume) ~1.3-1.5x faster per iteration than the
  two passes.  Parallelism is D work-items (fine on CPUs; a GPU would want
  the two-pass kernels).

* ``cbca_fused_multi_short`` (max_arm <= 8; the default on CPU devices,
  ``CBCA(ctx, multi=False)`` selects ``cbca_fused_short``): "temporal
  fusion", up to ``MULTI_K`` = 4 iterations per launch (a runtime count, so
  any number of iterations is launches of 4 and one shorter launch).  One
  work-item per plane walks down the rows once; at step t iteration i forms
  the row sums of its input row t - (i-1) max_arm and outputs row
  t - i max_arm, which is the input row of iteration i + 1 at the same step,
  so the volume is read once and written once per launch (4x fewer volume
  passes than ``cbca_fused_short``).  What every iteration shares is computed
  once per plane and row and kept in small per-plane rings: the combined arms
  l, r, u, w (bytes, capped at the borders), the row counts l + r + 1 and the
  cell count |U_d(p)| (as the float divisor).  Per iteration and 16-px chunk
  there remain 2 (2 max_arm + 1) masked adds (``s = select(s, s + v, take)``,
  one AVX-512 masked add; identical to ``s += select(0, v, take)`` because s
  starts at +0 and so is never -0; the arms are compared as signed bytes,
  which keeps the k = +-1 terms one masked add each instead of an add and a
  blend) and one division.  The next src row is fetched while the row-sum
  loops run, one chunk every 4 chunk steps (two row buffers), so its cache
  misses overlap arithmetic.  Bit-identical to iterating
  ``cbca_fused_short`` (float and half volumes; in half mode each
  iteration's output row is rounded to half before the next iteration reads
  it, as the volume round trip does).  Measured on PoCL (2 cores of an
  AMD EPYC with AVX-512), KITTI-size volume 228 x 367 x 1234, 4 iterations,
  best of 3 in one process: 476 ms (``cbca_fused_short``) -> 193 ms
  (2.4x; the volume copy alone takes ~36 ms).  Then (2026-11-23, PoCL
  3.1, real KITTI arms, shared 2-core machine, every figure an A/B best of
  4-5 in one process): the signed-byte masks (no blends), the next src row
  fetched over the row-sum loops (in one loop its misses had cost ~9 %)
  and the arms ring on uchar16 instead of int16: 186 -> 169 ms; the cell
  counts on ushort16 instead of int16: -> 161 ms; work-groups of one
  work-item on CPUs (see ``_get``): 161 -> 149 ms; the fetch in the
  row-sum loops only (not the column loops): 156 -> 150 ms; all together
  (the previous kernel at its previous work-group size) 194 -> 155-163
  ms per round (0.79-0.83x; in the pipeline the three KITTI rounds 187-193
  -> 145-160 ms), Intel's CPU runtime 196 -> 179 ms (0.91x).  Where the
  time goes (stub variants, same process): the column pass's masked adds
  ~28 %, the row pass's ~16 % (Zen 4 issues one 512-bit add per cycle),
  the arms ring ~13 % (every plane re-reads both images' arm planes; not
  cache misses: with the right arms read aligned with the left ones, or
  not at all, a round is 0-8 % faster, within ~2x the noise, so two planes
  per work-item sharing the left arms would save a few per cent at most),
  the src fetch and dst write now <= 2 % each, the
  division hidden, the rest loads, stores and loop overhead.  Tried without
  gain: one loop per iteration for both passes (slower), the fetch spread
  over the column loops too (3-5 % slower), the arms of row t + 1 computed
  over the row-sum loops (12-18 % slower), arms and counts in one loop,
  counts stored as floats (no conversion, more cache), a duplicated
  interleaved ring addressing the column pass's 7 rows from one pointer
  (~1 %).  Only D work-items, like
  ``cbca_fused_short``: a GPU keeps the two-pass kernels.

Tests compare all of them with the float64 set-definition reference at 1e-5
of the cost range, and the fused kernel bit for bit with the two passes.

Memory: no scratch volume (``CBCA.scratch_volumes`` = 0), also in place.
Pass 1 writes the row sums into the output (it may alias its input: each
cell is written after the values its window needs were read) and pass 2
works in place; iteration 1 reads ``d_cost``, later iterations the output.
The fused kernel writes row t - max_arm of a plane only after it read row t
of that plane, and only its own plane, so it works in place as well.  It
needs ``CBCA.scratch_bytes(D, W, max_arm, multi=False)`` = 5 D (2 max_arm + 1) W
bytes of rings (9.8 MB for D = 228, W = 1232, max_arm = 3), allocated on the
first call and kept (grown when needed) by the CBCA object.  The
multi-iteration kernel works in place too (dst row t - iters max_arm is
written at step t, after src row t was read); its per-plane scratch, with
WR = W rounded up to 16 and A = max_arm, is 4 (2A + 1) float rows (row-sum
rings of the 4 iterations), 3A + 1 ushort rows (cell counts), 5 (4A + 1) byte
rows (arms, row counts) and 3 float rows of WR + 32 cells (row buffers):
``CBCA.scratch_bytes(D, W, max_arm)`` (the default ``multi=True``, a bound
for both fused kernels) = 58.8 MB for D = 228, W = 1232, A = 3, i.e. 14.3 %
of that float32 volume (228 x 367 x 1232).  Rings and rows are 64-byte
aligned and accessed as whole vectors (PoCL splits vstore16 on unaligned
pointers, bytes one by one).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..cl import round_up
from .cross import ARM_LIMIT, check_size, launch, scan_local_size
from .disparity import volume_bytes

#: Largest max_arm served by the short-arm kernels (CBCA_SHORT_MAX in cbca.cl).
SHORT_MAX = 8
_VW = 16  # float16 lanes
_GROUPS = 8  # 16-column groups per work-item of cbca_columns_short (CBCA_GROUPS)
#: Iterations per launch of cbca_fused_multi_short (CBCA_K; its scratch grows with it).
MULTI_K = 4


class CBCA:
    """C^iterations_CBCA of a float32 [D][H][W] cost volume; see the module docstring.

    ``max_arm`` (``__call__`` argument, default 255, right for any arms): an
    upper bound of every arm length in the arm buffers; a program is built
    per value.  PASS THE TIGHT BOUND ``mccnn_cl.stages.cross.max_arm(eta,
    include_neighbor)`` (3 for the paper's eta = 4): it selects the fast
    short-arm kernels.  Arms longer than ``max_arm`` are truncated to it.
    ``short=False`` forces the running-sum kernels, ``fused=False`` the
    two-pass short-arm kernels (for comparisons); ``fused=None`` (default)
    takes the fused kernel on CPU devices only (it runs D work-items, too few
    for a GPU).  ``half=True``: volumes stored as half (``VOL_HALF``,
    kernels/common.h); sums stay float (the two-pass kernels store their row
    sums in the volume, so they round them to half too).
    ``__init__``'s ``max_arm`` only pre-builds that program.
    """

    #: Extra D x H x W volumes a call needs beyond ``d_cost`` and ``out``
    #: (for the memory planner): none, on every path, also when out is d_cost.
    scratch_volumes = 0

    def __init__(self, ctx, max_arm: int = ARM_LIMIT, short: bool = True, fused: bool | None = None,
                 half: bool = False, multi: bool | None = None):
        self.ctx = ctx
        self.short = bool(short)
        self._cpu = bool(ctx.device.type & ctx.cl.device_type.CPU)
        if fused is None:
            fused = self._cpu
            if ctx.is_rusticl:
                # Mesa 22.3's Rusticl/llvmpipe computes wrong sums in the fused
                # kernels on larger volumes (cost errors up to 1.0: the half
                # cbca_fused_short beyond ~170 rows; in float32 the multi-
                # iteration kernel at 100 x 632 and the one-iteration one at
                # 367 x 632, both exact at 64 x 96), while PoCL, Intel's
                # runtime and Oclgrind agree with the reference; its two-pass
                # kernels are right (tests/test_half.py,
                # tests/test_cbca.py::test_large_volume_default_path).  The
                # cause is llvmpipe's loop limit (65535 loop iterations per
                # work-item in all, then every loop ends silently; see
                # stages/sgm.py, LLVMPIPE_LOOP_LIMIT): a fused work-item walks a
                # whole plane and stops writing part way (docs/portability.md)
                fused = False
        self.fused = bool(fused)
        if multi is None:
            multi = self._cpu
        self.multi = bool(multi)
        self.half = bool(half)
        self._kernels = {}
        self._ring = None  # (nbytes, row-sum ring, count ring) of cbca_fused_short
        self._multi = None  # (sizes, [float, byte, row scratch]) of cbca_fused_multi_short
        self._get(max_arm)

    @staticmethod
    def scratch_bytes(D, W, max_arm=ARM_LIMIT, short=True, fused=True, multi=True) -> int:
        """Device bytes of the scratch a call allocates (and keeps for the next
        calls): the fused short-arm path's rings, D x (2 max_arm + 1) x W
        float32 row sums + as many byte counts (9.8 MB for D = 228, W = 1232,
        max_arm = 3: 2.3 % of that volume); 0 on the other paths."""
        max_arm = int(max_arm)
        if not (short and fused and max_arm <= SHORT_MAX):
            return 0
        if multi:
            return sum(_multi_scratch(D, W, max_arm))
        return 5 * int(D) * (2 * max_arm + 1) * int(W)

    def _get(self, max_arm):
        max_arm = int(max_arm)
        if not 0 <= max_arm <= ARM_LIMIT:
            raise InputError(f"max_arm must be in [0, {ARM_LIMIT}], got {max_arm}")
        short = max_arm <= SHORT_MAX and self.short
        fused = short and self.fused
        multi = fused and self.multi
        k = self._kernels.get((max_arm, short, fused, multi))
        if k is None:
            if multi:
                kern = self.ctx.kernel("cbca.cl", "cbca_fused_multi_short", MAX_ARM=max_arm, CBCA_K=MULTI_K,
                                       VOL_HALF=int(self.half))
                # A work-item walks a whole plane (~1.4 ms on KITTI), so on a
                # CPU work-groups of one spread the D planes evenly over the
                # cores; groups of the preferred multiple (8 on PoCL, 128 on
                # Intel's runtime: 2 groups for D = 228) left cores idle at
                # the end: 161 -> 149 ms on PoCL, 179 -> 154 ms on Intel.
                k = [(kern, 1 if self._cpu else scan_local_size(self.ctx, kern))]
            elif fused:
                kern = self.ctx.kernel("cbca.cl", "cbca_fused_short", MAX_ARM=max_arm, CBCA_GROUPS=_GROUPS,
                                       VOL_HALF=int(self.half))
                k = [(kern, scan_local_size(self.ctx, kern))]
            else:
                suffix = "_short" if short else ""
                defs = dict(MAX_ARM=max_arm, CBCA_GROUPS=_GROUPS) if short else dict(MAX_ARM=max_arm)
                defs["VOL_HALF"] = int(self.half)
                k = [self.ctx.kernel("cbca.cl", "cbca_rows" + suffix, **defs),
                     self.ctx.kernel("cbca.cl", "cbca_columns" + suffix, **defs)]
                k = [(kern, scan_local_size(self.ctx, kern)) for kern in k]
            k = (k, short, fused, multi)
            self._kernels[(max_arm, short, fused, multi)] = k
        return k

    def _rings(self, D, W, max_arm):
        """The fused path's scratch rings (kept and reused while large enough)."""
        nbytes = self.scratch_bytes(D, W, max_arm, multi=False)
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
        kerns, short, fused, multi = self._get(max_arm)
        if iterations == 0:
            if out is not d_cost:
                self.ctx.cl.enqueue_copy(self.ctx.queue, out, d_cost, byte_count=nbytes)
            return out
        dims = (np.int32(D), np.int32(H), np.int32(W))
        src = d_cost
        if multi:
            (k_multi, l_multi), = kerns
            scratch = self._multi_scratch(D, W, max_arm)
            done = 0
            while done < iterations:
                n = min(MULTI_K, iterations - done)
                launch(self.ctx, "CBCA", k_multi, (round_up(D, l_multi),), (l_multi,),
                       src, out, *scratch, d_arms_left, d_arms_right, *dims, np.int32(n))
                src = out
                done += n
            return out
        if fused:
            (k_fused, l_fused), = kerns
            ring, cring = self._rings(D, W, max_arm)
            for _ in range(iterations):
                launch(self.ctx, "CBCA", k_fused, (round_up(D, l_fused),), (l_fused,),
                       src, out, ring, cring, d_arms_left, d_arms_right, *dims)
                src = out
            return out
        (k_rows, l_rows), (k_cols, l_cols) = kerns
        for _ in range(iterations):
            launch(self.ctx, "CBCA rows", k_rows, (round_up(H, l_rows), D), (l_rows, 1),
                   src, out, d_arms_left, d_arms_right, *dims)
            ncol = -(-W // (_VW * _GROUPS)) if short else W
            launch(self.ctx, "CBCA columns", k_cols, (round_up(ncol, l_cols), D), (l_cols, 1),
                   out, d_arms_left, d_arms_right, *dims)
            src = out
        return out


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
