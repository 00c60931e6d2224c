"""Semi-global matching, SGM (paper, "Semiglobal matching") - drives ``kernels/sgm.cl``.

Along each direction r (left->right, right->left, top->bottom, bottom->top)::

    C_r(p, d) = C(p, d) - min_k C_r(p-r, k) + min{ C_r(p-r, d), C_r(p-r, d+-1) + P1,
                                                    min_k C_r(p-r, k) + P2 }
    C_SGM = (1/4) sum_r C_r

Validity by index, never by value: at p only d <= x exist; terms naming an
invalid cell of p - r are left out of the minima; a path's first pixel has
C_r = C; invalid output cells are NaN.  Penalties from D1 = |I^L(p) - I^L(p-r)|
and D2 = |I^R(pd) - I^R(pd-r)|, "large" when >= tau_so (:func:`penalty_table`):
``variant="paper"`` divides P1, P2 by q1 when one is large, by q2 when both
are; ``"code"`` (released code) by q1 q2 then; ``p2_times_pi1``: P2 = Pi1 Pi2;
P1 / v on the vertical paths; ``outside_large``: pd - r outside the right
image counts as a large D2 (released code).

Kernels: ``sgm_rows`` (a row per work-item, 16 x 16 tiles transposed to run
the recurrence on float16 lanes over d) and ``sgm_columns`` (``cols`` columns
per work-item, the path state in a (D + 2) x W scratch, so a path can be
walked in several launches) accumulate into the output in the order
C_lr, + C_rl, + C_tb, + C_bt, / 4; ``sgm_paired`` (two work-items, each adding
one horizontal and one vertical path per row, for devices with few compute
units) gives ((C_lr + C_tb) + (C_rl + C_bt)) / 4, equal to rounding.  The
defaults per device come from ``ctx.profile`` (mccnn_cl.opencl.device); under its
loop limit the paths are walked in bands.  :func:`.sgm_select.make_sgm` picks the stage
per device (SGM here, or :class:`.sgm_wg.SGMWorkGroup` for GPU-shaped
devices).  Measurements: BENCHMARKS.md, "History".
"""

from __future__ import annotations

import logging

import numpy as np

from ..opencl.context import launch, round_up
from ..opencl.device import LLVMPIPE_LOOP_LIMIT
from ..errors import InputError
from .cross import check_size
from .disparity import volume_bytes

log = logging.getLogger(__name__)

#: The paper's four directions r = (dx, dy), in the order accumulated.
DIRECTIONS = ((1, 0), (-1, 0), (0, 1), (0, -1))
_DISP_ROUND = 64
#: Most disparity levels SGM accepts: the kernels keep up to ~128 bytes of
#: private memory per level and work-item (2048 levels checked on PoCL).
MAX_LEVELS = 2048

# Under a loop limit (llvmpipe: LLVMPIPE_LOOP_LIMIT iterations per work-item
# in all, then every loop ends silently) the vertical paths are walked in
# bands of rows and the rows in ranges of chunks, their path state kept
# between launches; the two estimates below bound the iterations measured
# on llvmpipe (BENCHMARKS.md, "History").


def llvmpipe_column_band(max_disp, cols, limit=LLVMPIPE_LOOP_LIMIT) -> int:
    """Rows of the vertical path per sgm_columns launch under a loop limit of
    ``limit`` iterations per work-item: from an upper estimate of the
    iterations per row (3.5x or more the most measured on llvmpipe: ~7.4 per
    level and row at 32 columns, up to ~15 on partial strips)."""
    per_row = int(max_disp) * (8 * (int(cols) // 16) + 32) + 40 * ((int(max_disp) + int(cols)) // 16) + 128
    return max(1, int(limit) // per_row)


def llvmpipe_row_iterations(max_disp, W, both=False) -> int:
    """Upper estimate (~1.5x the measured, ~4.4 per level and 16-pixel chunk
    plus ~40) of the loop iterations of one sgm_rows work-item: 16-pixel
    chunks times (6 per level + 96)."""
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


def _max_disp(D, floor=_DISP_ROUND) -> int:
    """MAX_DISP compiled for D levels: D rounded up to a power of two, at least
    ``floor`` (a power of two; the device's rule ``sgm_disp_floor``: 256 on
    CPUs, else 64), so that the kernels are built for a few disparity counts
    at most (four from 256, six from 64, up to MAX_LEVELS) and a new D rarely
    needs a build.  MAX_DISP sizes private
    arrays only; the loops run over D.  A floor of 32 gave every D <= 32 builds
    of its own (~14 s for the one-direction kernels on a cold PoCL cache, a
    dozen of them in the test suite) for a call ~1 ms faster on small volumes
    (the paired sweeps, Zen 3, PoCL: 10.0 against 10.3 ms at D 16 on 288 x
    384, 22.2 against 23.4 ms at D 32 on 375 x 450, medians of 6 rounds)."""
    n = int(floor)
    while n < int(D):
        n *= 2
    return n


#: Columns per chunk of the paired sweeps (SGM_PAIR_CW in sgm.cl).
PAIR_CW = 16

#: The 16-bit sweeps (sgm_paired_q16): the scale s is the largest power of two with
#: (2 B + 2 P2) s <= Q16_SPAN for costs |C| <= B, so a pair's sum of C_r fits a short.
Q16_SPAN = 32000
#: ... and B s must reach this many steps (else the float sweeps run): the cost's resolution.
Q16_MIN_STEPS = 64


def q16_scale(cost_bound, pen_h, pen_v):
    """The scale s of the 16-bit sweeps for costs bounded by ``|C| <= cost_bound``
    and the penalty tables ``pen_h``, ``pen_v`` (:func:`penalty_table`): a power
    of two, or None where the costs would get fewer than Q16_MIN_STEPS steps
    (or the bound is not a positive finite number)."""
    b = float(cost_bound) if cost_bound is not None else float("nan")
    if not (np.isfinite(b) and b > 0):
        return None
    p2 = max(float(p) for p in tuple(pen_h[1]) + tuple(pen_v[1]))
    p1 = max(float(p) for p in tuple(pen_h[0]) + tuple(pen_v[0]))
    if not (np.isfinite(p2) and np.isfinite(p1) and p2 >= 0 and p1 >= 0):
        return None
    s = 2.0 ** np.floor(np.log2(Q16_SPAN / (2.0 * b + 2.0 * p2)))
    return float(s) if b * s >= Q16_MIN_STEPS else None


def q16_round(pen, s):
    """A penalty table in the 16-bit sweeps' integer steps (P s rounded to nearest even), as float32."""
    return tuple(tuple(np.float32(np.round(float(p) * s)) for p in half) for half in pen)


class SGM:
    """C_SGM of a float32 [D][H][W] cost volume; see the module docstring.

    Options (None: the device's default, ``ctx.profile.sgm_options()``; none
    of them changes a bit of the result, except ``paired``, equal to rounding):
    ``prefetch``: host prefetch instructions in the kernels (taken only where
    the kernel is compiled straight to x86 / AArch64, i.e. PoCL; elsewhere
    OpenCL's ``prefetch()`` hint).  ``band``: rows per band of the first sweep
    (0, the default: the whole image).  ``cols``: columns per ``sgm_columns``
    work-item, a multiple of 16.  ``fused_rows``: both row directions in one
    ``sgm_rows`` pass.  ``specialize``: the column kernel's inner loop compiled
    per output mode for its hot rows (after the first, the strip inside the
    image), the rest by one run-time copy.  ``whole_tiles``:
    whole 16 x 16 tiles of ``sgm_rows`` moved by plain vector loads and stores.
    ``paired``: the paired sweeps (``band``, ``cols``, ``fused_rows`` and
    ``specialize`` configure the one-direction kernels only).
    ``width``: the kernels' vectors, 16 or 8 floats (``SGM_VW``; the same bits).
    ``mirror_reads``: the right reference reads its volume mirrored through the
    paired sweeps (:attr:`reads_mirrored`) instead of mirroring it in place.
    ``loop_limit``: the most loop iterations a work-item may take in all (0:
    none); under a limit the one-direction kernels walk their paths in several
    launches (same results) and the paired sweeps refuse volumes beyond it.
    ``half=True``: volumes stored as half (``VOL_HALF``, kernels/common.h); the
    recurrences run in float, the partial sums in the output are rounded to half.
    ``int16``: a call given ``cost_bound`` (``|C| <= cost_bound`` in every valid
    cell; the pipeline's ``sgm_int16``) runs, where the stage has the paired
    sweeps and ``int16`` (rule ``sgm_int16``: CPUs), ``sgm_paired_q16``: the recurrences on 16-bit integers, the costs and
    penalties in steps of 1 / s (:func:`q16_scale`) rounded to nearest even, the
    result exactly float SGM of those rounded inputs (a NaN or a cost beyond the
    bound in a valid cell counts as the bound); :attr:`last_scale` is the s of the
    last call (None: float)."""

    def __init__(self, ctx, prefetch=None, half: bool = False, band=None, cols=None, fused_rows=None,
                 specialize=None, whole_tiles=None, paired=None, loop_limit=None, width=None, mirror_reads=None,
                 int16=None):
        self.ctx = ctx
        self.last_scale = None
        if loop_limit is not None and int(loop_limit) < 0:
            raise InputError(f"SGM loop_limit must be >= 0 (0: none), got {loop_limit}")
        rule = ctx.profile.sgm_options(loop_limit)
        self._loop_limit = rule["loop_limit"]

        def pick(value, name):
            return rule[name] if value is None else value

        self.prefetch = bool(pick(prefetch, "prefetch"))
        self.specialize = bool(pick(specialize, "specialize"))
        self.whole_tiles = bool(pick(whole_tiles, "whole_tiles"))
        self.fused_rows = bool(pick(fused_rows, "fused_rows"))
        self.paired = bool(pick(paired, "paired"))
        self.mirror_reads = bool(pick(mirror_reads, "mirror_reads"))
        self.int16 = bool(pick(int16, "int16"))
        width = pick(width, "width")
        if int(width) not in (8, 16):
            raise InputError(f"SGM width must be 8 or 16 floats, got {width}")
        self.width = int(width)
        self._group_of_one = rule["group_of_one"]
        band = 0 if band is None else band
        if int(band) < 0:
            raise InputError(f"SGM band must be >= 0 rows (0: the whole image), got {band}")
        self.band = int(band)
        cols = pick(cols, "cols")
        if int(cols) < 16 or int(cols) % 16:
            raise InputError(f"SGM cols must be a positive multiple of 16, got {cols}")
        self.cols = int(cols)
        self.disp_floor = int(rule["disp_floor"])
        self.half = bool(half)
        self._kernels = {}
        self._state = None
        self._rstate = None

    @property
    def reads_mirrored(self) -> bool:
        """Whether the right reference should call with ``mirror=True``: the
        stage can (the paired sweeps) and ``mirror_reads`` (rule
        ``sgm_mirror_reads``) prefers it to mirroring the volume in place."""
        return self.paired and self.mirror_reads

    def scratch_bytes(self, D, W, params=None) -> int:
        """Device scratch a call keeps besides the cost and output volumes (for
        the memory planner; ``params``, the Hyperparameters, change nothing
        here): :func:`state_bytes` of this configuration."""
        return state_bytes(D, W, self.cols, self.paired)

    def max_disp(self, D) -> int:
        """MAX_DISP the kernels are built with for D levels (:func:`_max_disp`, this device's floor)."""
        return _max_disp(D, self.disp_floor)

    def _kernel(self, D, names):
        """(kernel, local size) for each of ``names``, built for D levels."""
        max_disp = self.max_disp(D)
        k = self._kernels.get((max_disp, names))
        if k is None:
            k = [self.ctx.kernel("sgm.cl", name, MAX_DISP=max_disp, SGM_CPU_PREFETCH=int(self.prefetch),
                                 VOL_HALF=int(self.half), SGM_COLS=self.cols, SGM_SPECIALIZE=int(self.specialize),
                                 SGM_WHOLE_TILES=int(self.whole_tiles), SGM_PAIR_CW=PAIR_CW,
                                 SGM_VW=16 if names == ("sgm_paired_q16",) else self.width,
                                 SGM_PART={("sgm_paired",): 2, ("sgm_paired_q16",): 3}.get(names, 1))
                 for name in names]
            k = [(kern, self.ctx.profile.line_group(self.ctx, kern, self._group_of_one)) for kern in k]
            self._kernels[(max_disp, names)] = k
        return k

    def release_buffers(self):
        """Free the path-state scratch kept between calls (the next call makes it again)."""
        self._state = None
        self._rstate = None

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
                 out=None, mirror=False, cost_bound=None):
        """Enqueue the four directions; returns ``out`` (allocated when None,
        must not be ``d_cost``) holding C_SGM, NaN where invalid.

        ``mirror=True`` (the paired sweeps only; see :attr:`reads_mirrored`): run
        on the right-reference volume C_R'(d, y, x) = C(d, y, W - 1 + d - x)
        of ``d_cost`` = C without making it (``RightReference.volume`` would
        mirror C in place, a volume read and written, and again back); the
        same bits as SGM of the mirrored volume."""
        D, H, W = check_call(d_cost, D, H, W, out, mirror, self.paired)
        self.last_scale = None
        if out is None:
            out = self.ctx.empty(volume_bytes(self.half) * D * H * W, "SGM output volume")
        dims = (np.int32(D), np.int32(H), np.int32(W))
        bufs = (d_cost, d_img_left, d_img_right, out)
        pen_h = penalty_table(pi1, pi2, q1, q2, v, False, variant, p2_times_pi1)
        pen_v = penalty_table(pi1, pi2, q1, q2, v, True, variant, p2_times_pi1)
        if self.paired:
            if self._loop_limit is not None and \
                    3 * (H + 1) // 2 * llvmpipe_row_iterations(self.max_disp(D), W) // 2 > self._loop_limit:
                # a paired work-item walks half the rows whole (about 1.5x a row pass per row)
                raise InputError(f"SGM paired sweeps over {D} x {H} x {W} exceed the loop limit of "
                                 f"{self._loop_limit} iterations per work-item (loop_limit; llvmpipe's on "
                                 f"Rusticl): use paired=False there")
            scale = q16_scale(cost_bound, pen_h, pen_v) if self.int16 else None
            self.last_scale = scale
            ws = round_up(W, PAIR_CW)
            state = self._scratch("_state", state_bytes(D, W, paired=True), "SGM path state")
            if scale is not None:
                ((k_pair, _),) = self._kernel(D, ("sgm_paired_q16",))
                pen_h, pen_v = q16_round(pen_h, scale), q16_round(pen_v, scale)
                extra = (np.float32(scale), np.int32(np.floor(float(cost_bound) * scale)), np.float32(0.25 / scale))
                what = "SGM (paired sweeps, 16-bit)"
            else:
                ((k_pair, _),) = self._kernel(D, ("sgm_paired",))
                extra, what = (), "SGM (paired sweeps)"
            for launch_no in (0, 1):
                launch(self.ctx, what, k_pair, (2,), *bufs, state,
                       np.int32(ws), *dims, np.int32(H // 2), np.int32(launch_no), *pen_h[0], *pen_h[1],
                       *pen_v[0], *pen_v[1], np.float32(tau_so), np.int32(bool(outside_large)),
                       np.int32(bool(mirror)), *extra, local_size=(1,))
            return out
        (k_rows, l_rows), (k_cols, l_cols) = self._kernel(D, ("sgm_rows", "sgm_columns"))
        ws = round_up(W, self.cols)
        state = self._scratch("_state", state_bytes(D, W, self.cols), "SGM path state")
        g_cols = (round_up(ws // self.cols, l_cols),)

        nchunks = -(-W // self.width)
        hband = nchunks  # chunks of `width` columns per sgm_rows launch (llvmpipe's loop limit)
        rstate = state  # sgm_rows' state between chunk ranges (unused when hband = nchunks)

        def rows(dx, mode, y0, ny, both=0):
            for c0 in range(0, nchunks, hband):
                launch(self.ctx, "SGM (horizontal)", k_rows, (round_up(ny, l_rows),), *bufs, *dims,
                       np.int32(dx), *pen_h[0], *pen_h[1], np.float32(tau_so), np.int32(bool(outside_large)),
                       np.int32(mode), np.int32(y0), np.int32(ny), np.int32(both), np.int32(c0),
                       np.int32(c0 + hband), rstate, local_size=(l_rows,))

        def columns(dy, mode, j0, nj):
            launch(self.ctx, "SGM (vertical)", k_cols, g_cols, *bufs, state, np.int32(ws), *dims,
                   np.int32(j0), np.int32(nj), np.int32(dy), *pen_v[0], *pen_v[1], np.float32(tau_so), np.int32(mode),
                   local_size=(l_cols,))

        # vertical paths in launches of at most vband rows (llvmpipe's loop limit)
        vband = H
        fused = self.fused_rows
        if self._loop_limit is not None:
            vband = llvmpipe_column_band(self.max_disp(D), self.cols, self._loop_limit)
            if llvmpipe_row_iterations(self.max_disp(D), W, self.fused_rows) > self._loop_limit:
                # walk the rows in ranges of chunks, one direction per launch
                fused = False
                hband = max(1, self._loop_limit // llvmpipe_row_iterations(self.max_disp(D), self.width))
                if hband < nchunks:
                    # SGM_RST = MAX_DISP + 19 floats per row (sgm.cl)
                    rstate = self._scratch("_rstate", 4 * H * (self.max_disp(D) + 19), "SGM row path state")

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


def check_call(d_cost, D, H, W, out, mirror=False, reads_mirrored=False) -> tuple:
    """(D, H, W) of an SGM stage's call, checked (both stages): 1 <= D <= MAX_LEVELS, not in place,
    ``mirror=True`` only for a stage that ``reads_mirrored``."""
    if mirror and not reads_mirrored:
        raise ValueError("SGM mirror=True needs the paired sweeps (paired=True)")
    H, W = check_size(H, W, "cost volume")
    D = int(D)
    if not 1 <= D <= MAX_LEVELS:
        raise InputError(f"SGM takes 1 to {MAX_LEVELS} disparity levels, got D = {D}")
    if out is not None and out is d_cost:
        raise InputError("SGM cannot work in place: out must differ from d_cost")
    return D, H, W


def state_bytes(D, W, cols=32, paired=False) -> int:
    """The vertical paths' state: (D + 2) rows of W (rounded up to ``cols``)
    floats; with ``paired``, two such states (W rounded up to PAIR_CW).  Under
    a loop limit ``sgm_rows`` may also keep (MAX_DISP + 19) floats per row
    between launches, not counted here (~1 KB per row)."""
    if paired:
        return 4 * 2 * (int(D) + 2) * round_up(int(W), PAIR_CW)
    return 4 * (int(D) + 2) * round_up(int(W), int(cols))
