"""Semi-global matching, SGM (paper, "Semiglobal matching") - drives
``kernels/sgm.cl`` (kernels ``sgm_rows`` and ``sgm_columns``, one launch per
direction, or ``sgm_paired``, two launches for all four).

Recurrence along each of the four directions r (left->right, right->left,
top->bottom, bottom->top; p - r is the previous pixel on the path)::

    C_r(p, d) = C(p, d) - min_k C_r(p-r, k)
                + min{ C_r(p-r, d), C_r(p-r, d-1) + P1, C_r(p-r, d+1) + P1,
                       min_k C_r(p-r, k) + P2 }
    C_SGM = (1/4) sum_r C_r

Validity (by index, never by value): at p only d <= x exist (d < D); terms
naming an invalid cell of p - r (d, d +- 1 or k beyond its valid range) are
left out of the minima; the first pixel of each path has C_r = C; invalid
output cells are NaN.

Penalties, D1 = |I^L(p) - I^L(p-r)|, D2 = |I^R(pd) - I^R(pd-r)|, a gradient
being "large" when >= tau_so:

* ``variant="paper"`` (default): P1 = Pi1, P2 = Pi2 when both are small;
  both / q1 when exactly one is large; both / q2 when both are.
* ``variant="code"`` (released code, NOTES.md): / q1 when one is large,
  / (q1 * q2) when both are.
* ``p2_times_pi1=True``: P2 = Pi1 * Pi2 instead of Pi2 (identical at the
  default Pi1 = 1).
* P1 is additionally divided by v on the vertical paths (paper: "halved";
  the released code's asymmetric application is not reproduced).
* pd - r outside the right image (the paper is silent; only on the
  left->right path, at d = x): D2 counts as large (``outside_large=True``,
  default, as in the released code: the right pixel has no predecessor, so
  nothing argues for smoothness there, and this keeps the weaker penalties
  at the left border, where disparity jumps of occluded regions occur);
  ``outside_large=False`` treats it as small.

Defaults: Pi1 = 1, Pi2 = 32, tau_so = 0.0625 (images in [0, 1]), q1 = 4,
q2 = 10, v = 2.

Implementation (see ``kernels/sgm.cl``): x is the only contiguous axis of
[d][y][x], so both kernels move 16-wide chunks along x.  ``sgm_rows`` walks
one row per work-item, copying each chunk of all D planes into private
memory transposed to [x][d] (16 x 16 tiles transposed in registers) and
running the recurrence on float16 lanes over d, C_r overwriting the costs
in the block before it is transposed back and combined with the output;
the right-image gradient decisions are taken once per chunk (stored
reversed, so a pixel's 16 levels are one vector load).  With ``both`` it
then walks the same row the other way, adding to the output while the row
is still in the cache (``fused_rows``, default on CPUs).  ``sgm_columns``
walks ``cols`` adjacent columns per work-item (groups of 16 on float16
lanes over x: ``cols`` contiguous elements of each plane per step); the
path's state between rows, C_r(p - r, .) and its minimum, lives in a global
(D + 2) x W buffer (``SGM.scratch_bytes``), so a path can be walked in
several launches (``band``) and the kernel keeps no large private arrays;
C_r(p - r, d + 1) is carried to the next level in registers and the
right-image gradient flags are computed once per row.  ``sgm_rows`` keeps
~76 bytes of private memory per level (about 21 KB at MAX_DISP = 256, i.e.
KITTI's D = 228).  The launches accumulate straight into the output in the
order C_lr (written), + C_rl, + C_tb, + C_bt and / 4, so no per-direction
volume is stored and the sums are rounded exactly as before.  Each step
reads one line in each of D planes, which no hardware prefetcher follows:
on CPU devices whose compiler targets the CPU's instruction set (PoCL) the
kernels prefetch the next step's lines (``prefetch``, below); elsewhere they
give OpenCL's ``prefetch()`` hint.  fmin is written as one comparison where
an argument is known never to be NaN (the same value, ties included).

Paired sweeps (``paired``, kernel ``sgm_paired``; the default on CPU
devices with at most PAIRED_MAX_UNITS = 2 compute units, not on Rusticl):
two work-items per launch, two launches.  Work-item A walks rows top to
bottom and adds the left->right and top->bottom paths of each row, B walks
rows bottom to top with right->left and bottom->top; in the first launch A
takes rows 0 .. H/2 - 1 and B the others, each writing its pair's sum, in
the second each walks on through the other's rows (its vertical state kept
in the scratch) adding its sum and dividing by 4.  So every cell is
((C_lr + C_tb) + (C_rl + C_bt)) / 4: the same values to rounding (tested
against the reference and the one-direction kernels at the same tolerance),
not bit for bit.  Per row and 16-column chunk, in the horizontal path's
order, the chunk's costs are loaded as 16 x 16 tiles, the vertical
recurrence runs on the tiles' rows (lanes over x, its state one contiguous
[D + 2][16] block per 16 columns), the tiles are transposed for the
horizontal recurrence as in ``sgm_rows`` and transposed back, and the two
paths' sum written.  The volume is read twice and the output written twice
and read once, against four reads of the volume, three of the output and
four writes for the one-direction kernels; but only two work-items run,
hence the compute-unit limit.  Measured on PoCL (2 cores, KITTI D = 228,
367 x 1234, A/B in one process, best of 3): one SGM call 269-297 ms ->
204-213 ms (two launches of ~102 ms), then 194-200 ms (against 285-296 for
the one-direction kernels in the same runs) once the vertical recurrence's
loop over a tile's 16 levels had a constant trip count (so the tile stays
in registers).  Of those, ~35 ms are the transposes and ~20 ms the
vertical recurrence; with every computation stubbed out the loads and
stores alone take ~150 ms.  Then the next chunk's lines prefetched into
the L2 cache only (``prefetcht1``; the other kernels keep ``prefetcht0``,
with which they are faster): 196-201 -> 144-156 ms, against 285-304 ms for
the one-direction kernels in the same runs (0.50x).  Intel's CPU runtime
(its own ``prefetch()``) runs the kernel in 154-162 ms.  Tried for the
transposes: the classic unpack / 128-bit-lane form and four 8 x 8 float8
transposes (LLVM 15 in PoCL emits the same permutes for the former; both
cut the kernel's arithmetic when its memory accesses are stubbed out,
150 -> 128-141 ms, but not the real call: 199 -> 203 and 221 ms); on
Intel's runtime the unpack form is faster (154 -> 135 ms), not used.
Tried and slower or no better: reading the right reference's volume
mirrored straight from the left one (bit-identical, saves the 33 ms mirror
copy, but the call took 298-318 ms instead of 193-203, even with whole-tile
loads for the diagonal tiles); prefetching 2 or 3 chunks ahead (no
change); 32-, 64- or 128-column chunks (257-283 ms, although a bare
load/add/store walk gets faster with wider runs per plane); bands of 4-16
rows walked chunk by chunk (285-328 ms: each chunk then touches D pages per
row of the band, more than the TLB holds); prefetching the state's lines
(+5 ms).

Defaults of the one-direction kernels by device type (results identical
bit for bit, tested): CPU devices walk 128 columns per ``sgm_columns``
work-item (32 elsewhere, for W / 32 work-items), work-groups of 1 (PoCL runs each group on one thread:
few large work-items in groups of 8 left a core idle), fused row passes,
and the whole image as one band (bands of rows, meant to keep a band in the
cache for the vertical path, measured slower on PoCL: the row launches get
too few work-items).

Measured on PoCL, 2 cores (AMD EPYC VM), KITTI D = 228, 367 x 1234, best of
3 per launch, A/B in one process, bit-identical outputs: before, 580-720 ms
per call (sgm_rows 133 + 84 ms, sgm_columns 177 + 177 ms); now 320-330 ms
(one fused sgm_rows launch ~175 ms, sgm_columns ~70-75 ms each).  Later in
the same session, with the machine's memory visibly slower (a load/store-only
walk twice as slow, the plain copy not), 535-575 ms against 575-1010 ms for
the old kernels.  A walk that only loads and stores in sgm_columns' pattern
costs ~70-80 ms per read-read-write pass (sgm_rows' pattern ~73 ms), so the
vertical kernel is near its memory traffic; the row kernel is about half
arithmetic (transposes, a serial minimum per pixel).

sgm_rows on the same machine (2026-11-23 evening, KITTI size as above, A/B
in one process, best of 3, three rounds; a variant of the kernel for each
measurement, its outputs wrong where it skips work): skipping the recurrence
altogether changes the launch by less than the noise (~170 ms either way);
skipping the transposes saves ~40 ms; loading every chunk's costs from one
cached place saves ~30 ms, and ~10 ms more with the output too.  So the
launch is bound by moving the chunks (loads that wait for memory although
prefetched, transposes, index arithmetic), not by the serial minimum; the
d - 1 / d + 1 neighbours shuffled from aligned vectors instead of misaligned
loads, unpack-pattern transposes (LLVM emits the same vpermt2ps), prefetching
2 or 3 chunks ahead, both lines of a misaligned chunk, write intent or L2
hints: no measurable change.  Whole tiles moved by plain loads and stores
(``whole_tiles``): sgm_rows 167-173 -> 158-160 ms, the SGM call 311-322 ->
302-319 ms; Intel's CPU runtime 159-203 -> 141-165 ms (noisier).
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import InputError
from ..cl import round_up
from .cross import check_size, launch, scan_local_size
from .disparity import volume_bytes

log = logging.getLogger(__name__)

#: The paper's four directions r = (dx, dy), in the order accumulated.
DIRECTIONS = ((1, 0), (-1, 0), (0, 1), (0, -1))
_DISP_ROUND = 32
#: Most disparity levels SGM accepts: the kernels keep up to ~128 bytes of
#: private memory per level and work-item (2048 levels checked on PoCL).
MAX_LEVELS = 2048
_COLS = 32  # default columns per work-item in sgm_columns (two groups of VW = 16 lanes in sgm.cl)
#: Rows per band of the first sweep on CPU devices (module docstring).
BAND_CPU = 0
#: Columns per work-item of sgm_columns on CPU devices: longer runs of each
#: plane per step (module docstring).
COLS_CPU = 128


#: Mesa's llvmpipe (the device of Rusticl here; gallivm's
#: LP_MAX_TGSI_LOOP_ITERATIONS, Mesa 22.3.6) gives every work-item one
#: counter of loop iterations, shared by all loops of the kernel, and ends
#: each loop silently (no error) once that work-item has taken 65535 loop
#: iterations in all; each later loop then runs one iteration at most.  An
#: SGM work-item walks a whole path, so on llvmpipe the vertical paths are
#: walked in bands of rows (the path state is kept between launches anyway)
#: and each row pass gets its own launch.  Measured on llvmpipe: sgm_columns
#: takes about 7.4 loop iterations per level and row at 32 columns (5.6 at
#: 16), up to ~15 on partial strips at the right border in the adding modes;
#: sgm_rows about 4.4 per level per 16-pixel chunk, plus ~40 per chunk, so a
#: row pass would be cut short at KITTI's size (D = 228, W = 1234: wrong from
#: pixel 1040 on); there the rows are walked in ranges of chunks, their path
#: state kept between launches.
LLVMPIPE_LOOP_LIMIT = 65535


def llvmpipe_column_band(max_disp, cols, limit=LLVMPIPE_LOOP_LIMIT) -> int:
    """Rows of the vertical path per sgm_columns launch under a loop limit of
    ``limit`` iterations per work-item: from an upper estimate of the
    iterations per row (3.5x or more the most measured on llvmpipe, see
    above)."""
    per_row = int(max_disp) * (8 * (int(cols) // 16) + 32) + 40 * ((int(max_disp) + int(cols)) // 16) + 128
    return max(1, int(limit) // per_row)


def llvmpipe_row_iterations(max_disp, W, both=False) -> int:
    """Upper estimate (~1.5x the measured) of the loop iterations of one
    sgm_rows work-item: 16-pixel chunks times (6 per level + 96)."""
    return (1 + int(bool(both))) * -(-int(W) // 16) * (6 * int(max_disp) + 96)


def penalty_table(pi1=1.0, pi2=32.0, q1=4.0, q2=10.0, v=2.0, vertical=False, variant="paper",
                  p2_times_pi1=False):
    """((P1 for 0, 1, 2 large gradients), (P2 likewise)) as float32."""
    if variant not in ("paper", "code"):
        raise InputError(f"SGM variant must be 'paper' or 'code', got {variant!r}")
    div = (1.0, float(q1), float(q2) if variant == "paper" else float(q1) * float(q2))
    p2 = float(pi1) * float(pi2) if p2_times_pi1 else float(pi2)
    p1s = tuple(np.float32(float(pi1) / f / (float(v) if vertical else 1.0)) for f in div)
    p2s = tuple(np.float32(p2 / f) for f in div)
    return p1s, p2s


def _max_disp(D) -> int:
    """MAX_DISP compiled for D levels (D rounded up to a multiple of 32)."""
    return -(-int(D) // _DISP_ROUND) * _DISP_ROUND


#: ``SGM(paired=None)`` takes the paired sweeps on CPU devices with at most
#: this many compute units (two work-items per launch; module docstring).
PAIRED_MAX_UNITS = 2
#: Columns per chunk of the paired sweeps (SGM_PAIR_CW in sgm.cl).
PAIR_CW = 16


class SGM:
    """C_SGM of a float32 [D][H][W] cost volume; see the module docstring.

    ``prefetch``: use CPU prefetch instructions (clang's ``__builtin_prefetch``)
    in the kernels; None (default) does so on devices whose type is exactly
    CPU (not Oclgrind, which reports CPU | GPU), and the kernel takes them only
    where it is compiled straight to x86 / AArch64 (PoCL; not SPIR or SPIR-V
    compilers such as Intel's CPU runtime or Rusticl).  Hints only: the
    results are the same either way.

    ``band``: rows per band of the first sweep (see the module docstring);
    None (default) picks BAND_CPU rows on CPU devices and the whole image
    elsewhere.  ``cols``: columns per work-item of ``sgm_columns`` (a
    multiple of 16; default COLS_CPU = 128 on CPU devices, 32 elsewhere and
    on Rusticl).  ``specialize``: compile the column kernel's inner row
    loop once per (first row, output mode, strip inside the image)
    combination (~7 % faster on PoCL); default on, except on Rusticl, whose
    llvmpipe compiler takes minutes on it.  ``whole_tiles``: move whole
    16 x 16 tiles in ``sgm_rows`` by a separate path of plain vector loads
    and stores (~9 % faster on PoCL); default on, except on Rusticl (its
    compile time, ~+30 % for the SGM portability case).  None of these
    changes a bit of the result.

    ``paired``: the paired sweeps (module docstring; two work-items, so
    meant for devices with few compute units); None (default) takes them on
    CPU devices with at most PAIRED_MAX_UNITS compute units, except on
    Rusticl.  ``band``, ``cols``, ``fused_rows`` and ``specialize``
    configure the one-direction kernels only.

    ``loop_limit``: the most loop iterations a work-item may take in all
    (0: no limit); None (default) is LLVMPIPE_LOOP_LIMIT on Rusticl, no limit
    elsewhere.  Under a limit the one-direction kernels walk their paths in
    several launches (same results, bit for bit) and the paired sweeps
    refuse volumes beyond it.

    ``half=True``: volumes stored as half (``VOL_HALF``, kernels/common.h);
    the recurrences run in float, and the output accumulates the four
    directions in place, so the partial sums are rounded to half too."""

    def __init__(self, ctx, prefetch=None, half: bool = False, band=None, cols=None, fused_rows=None,
                 specialize=None, whole_tiles=None, paired=None, loop_limit=None):
        self.ctx = ctx
        # Mesa's llvmpipe (Rusticl) compiles the column kernel at its first
        # launch, and takes minutes on the specialised 128-column CPU variant
        # (~190 s at MAX_DISP = 32; ~4 s unspecialised at 32 columns)
        slow_compiler = ctx.is_rusticl
        # llvmpipe ends a work-item's loops after 65535 iterations in all
        # (LLVMPIPE_LOOP_LIMIT): the vertical paths are walked in bands of rows
        # there, the row passes one direction per launch (__call__)
        if loop_limit is None:
            loop_limit = LLVMPIPE_LOOP_LIMIT if ctx.is_rusticl else 0
        if int(loop_limit) < 0:
            raise InputError(f"SGM loop_limit must be >= 0 (0: none), got {loop_limit}")
        self._loop_limit = int(loop_limit) or None
        if specialize is None:
            specialize = not slow_compiler
        self.specialize = bool(specialize)
        if whole_tiles is None:
            whole_tiles = not slow_compiler
        self.whole_tiles = bool(whole_tiles)
        self.half = bool(half)
        self._kernels = {}
        is_cpu = self._cpu = int(ctx.device.type) == int(ctx.cl.device_type.CPU)
        if prefetch is None:
            prefetch = is_cpu
        self.prefetch = bool(prefetch)
        if band is None:
            band = BAND_CPU if is_cpu else 0
        if int(band) < 0:
            raise InputError(f"SGM band must be >= 0 rows (0: the whole image), got {band}")
        self.band = int(band)
        if cols is None:
            cols = COLS_CPU if is_cpu and not slow_compiler else _COLS
        if int(cols) < 16 or int(cols) % 16:
            raise InputError(f"SGM cols must be a positive multiple of 16, got {cols}")
        self.cols = int(cols)
        if fused_rows is None:
            fused_rows = is_cpu and self._loop_limit is None
        self.fused_rows = bool(fused_rows)
        if paired is None:
            paired = is_cpu and not slow_compiler and int(ctx.device.max_compute_units) <= PAIRED_MAX_UNITS
        self.paired = bool(paired)
        self._state = None
        self._rstate = None

    @staticmethod
    def scratch_bytes(D, W, cols=COLS_CPU, paired=False) -> int:
        """Device scratch besides the cost and output volumes: the vertical
        paths' state, (D + 2) rows of W (rounded up to ``cols``) floats; with
        ``paired``, two such states (W rounded up to PAIR_CW).  Under a loop
        limit (Rusticl) ``sgm_rows`` may also keep (MAX_DISP + 19) floats per
        row between launches, not counted here (~1 KB per row)."""
        if paired:
            return 4 * 2 * (int(D) + 2) * round_up(int(W), PAIR_CW)
        return 4 * (int(D) + 2) * round_up(int(W), int(cols))

    def _kernel(self, D, names):
        """(kernel, local size) for each of ``names``, built for D levels."""
        max_disp = _max_disp(D)
        k = self._kernels.get((max_disp, names))
        if k is None:
            k = [self.ctx.kernel("sgm.cl", name, MAX_DISP=max_disp, SGM_CPU_PREFETCH=int(self.prefetch),
                                 VOL_HALF=int(self.half), SGM_COLS=self.cols, SGM_SPECIALIZE=int(self.specialize),
                                 SGM_WHOLE_TILES=int(self.whole_tiles), SGM_PAIR_CW=PAIR_CW)
                 for name in names]
            k = [(kern, 1 if self._cpu else scan_local_size(self.ctx, kern)) for kern in k]
            self._kernels[(max_disp, names)] = k
        return k

    def _scratch(self, attr, nbytes, what):
        """The device buffer kept in ``self.<attr>``, replaced by a larger one
        when it holds fewer than ``nbytes`` bytes."""
        buf = getattr(self, attr)
        if buf is None or buf.size < nbytes:
            setattr(self, attr, None)  # release the old buffer before the new one is allocated
            buf = self.ctx.empty(nbytes, what)
            setattr(self, attr, buf)
        return buf

    def __call__(self, d_cost, d_img_left, d_img_right, D, H, W, pi1=1.0, pi2=32.0, tau_so=0.0625,
                 q1=4.0, q2=10.0, v=2.0, variant="paper", p2_times_pi1=False, outside_large=True,
                 out=None):
        """Enqueue the four directions; returns ``out`` (allocated when None,
        must not be ``d_cost``) holding C_SGM, NaN where invalid."""
        H, W = check_size(H, W, "cost volume")
        D = int(D)
        if not 1 <= D <= MAX_LEVELS:
            raise InputError(f"SGM takes 1 to {MAX_LEVELS} disparity levels, got D = {D}")
        if out is not None and out is d_cost:
            raise InputError("SGM cannot work in place: out must differ from d_cost")
        if out is None:
            out = self.ctx.empty(volume_bytes(self.half) * D * H * W, "SGM output volume")
        dims = (np.int32(D), np.int32(H), np.int32(W))
        bufs = (d_cost, d_img_left, d_img_right, out)
        pen_h = penalty_table(pi1, pi2, q1, q2, v, False, variant, p2_times_pi1)
        pen_v = penalty_table(pi1, pi2, q1, q2, v, True, variant, p2_times_pi1)
        if self.paired:
            if self._loop_limit is not None and \
                    3 * (H + 1) // 2 * llvmpipe_row_iterations(_max_disp(D), W) // 2 > self._loop_limit:
                # a paired work-item walks half the rows whole (about 1.5x a row pass per row)
                raise InputError(f"SGM paired sweeps over {D} x {H} x {W} exceed the loop limit of "
                                 f"{self._loop_limit} iterations per work-item (loop_limit; llvmpipe's on "
                                 f"Rusticl): use paired=False there")
            ((k_pair, _),) = self._kernel(D, ("sgm_paired",))
            ws = round_up(W, PAIR_CW)
            state = self._scratch("_state", self.scratch_bytes(D, W, paired=True), "SGM path state")
            for launch_no in (0, 1):
                launch(self.ctx, "SGM (paired sweeps)", k_pair, (2,), (1,), *bufs, state,
                       np.int32(ws), *dims, np.int32(H // 2), np.int32(launch_no), *pen_h[0], *pen_h[1],
                       *pen_v[0], *pen_v[1], np.float32(tau_so), np.int32(bool(outside_large)))
            return out
        (k_rows, l_rows), (k_cols, l_cols) = self._kernel(D, ("sgm_rows", "sgm_columns"))
        ws = round_up(W, self.cols)
        state = self._scratch("_state", self.scratch_bytes(D, W, self.cols), "SGM path state")
        g_cols = (round_up(ws // self.cols, l_cols),)

        nchunks = -(-W // 16)
        hband = nchunks  # chunks of 16 columns per sgm_rows launch (llvmpipe's loop limit)
        rstate = state  # sgm_rows' state between chunk ranges (unused when hband = nchunks)

        def rows(dx, mode, y0, ny, both=0):
            for c0 in range(0, nchunks, hband):
                launch(self.ctx, "SGM (horizontal)", k_rows, (round_up(ny, l_rows),), (l_rows,), *bufs, *dims,
                       np.int32(dx), *pen_h[0], *pen_h[1], np.float32(tau_so), np.int32(bool(outside_large)),
                       np.int32(mode), np.int32(y0), np.int32(ny), np.int32(both), np.int32(c0),
                       np.int32(c0 + hband), rstate)

        def columns(dy, mode, j0, nj):
            launch(self.ctx, "SGM (vertical)", k_cols, g_cols, (l_cols,), *bufs, state, np.int32(ws), *dims,
                   np.int32(j0), np.int32(nj), np.int32(dy), *pen_v[0], *pen_v[1], np.float32(tau_so), np.int32(mode))

        # vertical paths in launches of at most vband rows (llvmpipe's loop limit)
        vband = H
        fused = self.fused_rows
        if self._loop_limit is not None:
            vband = llvmpipe_column_band(_max_disp(D), self.cols, self._loop_limit)
            if llvmpipe_row_iterations(_max_disp(D), W, self.fused_rows) > self._loop_limit:
                # walk the rows in ranges of chunks, one direction per launch
                fused = False
                hband = max(1, self._loop_limit // llvmpipe_row_iterations(_max_disp(D), 16))
                if hband < nchunks:
                    # SGM_RST = MAX_DISP + 19 floats per row (sgm.cl)
                    rstate = self._scratch("_rstate", 4 * H * (_max_disp(D) + 19), "SGM row path state")

        def columns_banded(dy, mode, j0, nj):
            for j in range(j0, j0 + nj, vband):
                columns(dy, mode, j, min(vband, j0 + nj - j))

        # first sweep, top to bottom in bands: C_lr, + C_rl, + C_tb (the band's
        # rows are still in the cache when the vertical path reaches them)
        band = self.band or H
        for y0 in range(0, H, band):
            ny = min(band, H - y0)
            if fused:
                rows(1, 0, y0, ny, both=1)
            else:
                rows(1, 0, y0, ny)
                rows(-1, 1, y0, ny)
            columns_banded(1, 1, y0, ny)
        # second sweep: + C_bt, divided by 4
        columns_banded(-1, 2, 0, H)
        return out
