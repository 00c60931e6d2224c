"""Every stage kernel once under Oclgrind (out-of-bounds accesses, data races,
uninitialised reads, API misuse), on tiny inputs.

Each case runs in a SUBPROCESS (this file run as a script, see ``main``) whose
ICD loader sees only Oclgrind (``OCL_ICD_VENDORS`` = the oclgrind ``.icd``
written by ``scripts/opencl_impls.sh``) with ``OCLGRIND_DATA_RACES=1``,
``OCLGRIND_CHECK_API=1``, ``OCLGRIND_LOG=<file>`` and ``PYOPENCL_NO_CACHE=1``.
Oclgrind never aborts a kernel: it logs.  So a case FAILS when the log is not
empty, when the subprocess's comparison with the numpy reference fails, or
when Oclgrind reports an API error on stderr (minus one benign pyopencl probe,
see ``conftest.OCLGRIND_BENIGN``).  Oclgrind missing is a failure with an
install hint (``scripts/test.sh`` installs it).

The same worker runs the cases on any implementation
(``python tests/test_oclgrind.py --impl rusticl --all``); test_portability.py
uses that for Rusticl, through ``helpers.run_isolated``; the kernels each
case must fetch are ``helpers.CASE_KERNELS`` (shared with test_portability.py),
and ``helpers.CASE_FORMS`` the build options some must fetch them with (the
cpu rules column's forms, forced whatever the device's rules pick), so that
every case fetches the same kernels and forms on any implementation.

Inputs are tiny (Oclgrind interprets every work-item, ~1000x slower than
PoCL): images of 12 x 20 (cropped domain 4 x 12) and 13 x 21, D = 5, plus one
D >= W volume.  Each case also poisons its outputs first, so an element the
kernel leaves unwritten fails the comparison.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from helpers import CASE_FORMS, CASE_KERNELS, NOT_BUILT_ON, run_isolated

HERE = Path(__file__).resolve().parent
POISON = np.float32(-1.2345e30)  # same value as conftest.POISON (not imported: worker runs standalone)
IPOISON = np.int32(-123456789)


# ---------------------------------------------------------------------------
# helpers used by the cases (run inside the worker process)
# ---------------------------------------------------------------------------
def _images(rng, h, w):
    """A random left image and a right image that is it shifted by ~2 px plus noise."""
    left = rng.random((h, w)).astype(np.float32)
    right = np.roll(left, -2, axis=1) * 0.9 + 0.1 * rng.random((h, w)).astype(np.float32)
    assert np.ptp(left) > 0 and np.ptp(right) > 0
    return left, right.astype(np.float32)


def _volume(rng, D, H, W):
    """Random cost volume in [0, 1) with NaN in the invalid cells (x < d)."""
    C = rng.random((D, H, W)).astype(np.float32)
    for d in range(D):
        C[d, :, :min(d, W)] = np.nan
    return C


def _poisoned(ctx, nbytes, dtype=np.float32):
    buf = ctx.empty(nbytes, "test output")
    ctx.fill(buf, POISON if dtype == np.float32 else IPOISON, nbytes, dtype=dtype)
    return buf


def _volume_and_output(ctx, C, half):
    """(C, a poisoned output volume of its shape): float32, or with ``half`` C as
    float16 and the output poisoned with half's most negative finite value."""
    if not half:
        return C, _poisoned(ctx, 4 * C.size)
    out = ctx.empty(2 * C.size, "test output")
    ctx.fill(out, -65504.0, 2 * C.size, np.float16)
    return C.astype(np.float16), out


class Checks:
    """Collects comparisons; ``failures`` lists the ones that failed."""

    def __init__(self):
        self.results = []

    def close(self, name, got, want, atol=0.0, rtol=0.0):
        got, want = np.asarray(got), np.asarray(want)
        ok = got.shape == want.shape
        err = None
        if ok:
            nan_ok = np.array_equal(np.isnan(got), np.isnan(want)) if got.dtype.kind == "f" else True
            if got.dtype.kind in "iu" or (atol == 0 and rtol == 0):
                same = np.array_equal(got, want, equal_nan=got.dtype.kind == "f")
                err = int(np.sum(got != want)) if got.dtype.kind in "iu" else None
                ok = bool(same)
            else:
                m = ~np.isnan(want)
                diff = np.abs(got[m].astype(np.float64) - want[m].astype(np.float64))
                lim = atol + rtol * np.abs(want[m].astype(np.float64))
                err = float(diff.max()) if diff.size else 0.0
                ok = bool(nan_ok and np.all(diff <= lim))
        self.results.append({"name": name, "ok": ok, "shape": list(got.shape), "err": err})

    def differs(self, name, a, b):
        """Records a failure when ``a`` equals ``b``: an input that must reach a
        path (a range that changes the reference's answer) and no longer does."""
        self.results.append({"name": name, "ok": not np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True),
                             "shape": list(np.shape(a)), "err": None})

    @property
    def failures(self):
        return [r for r in self.results if not r["ok"]]


# ---------------------------------------------------------------------------
# cases: one per stage (or per kernel file); each takes (ctx, rng, checks)
# ---------------------------------------------------------------------------
def case_network(ctx, rng, chk):
    """network_conv.cl + network_head.cl: a tiny random net (9x9 patch)."""
    from mccnn_cl.reference import network as ref
    from mccnn_cl.costs.network import NetworkCost
    from mccnn_cl.stages.sgm import SGM
    from mccnn_cl.stages.sgm_wg import SGMWorkGroup
    from mccnn_cl.weights import Weights

    w = Weights.random(conv_layers=[[4, 3], [4, 3], [4, 3], [4, 3]], fc_layers=[8, 8, 8, 2], seed=3)
    # 20 maps and hidden units: with RN 16 a whole and a partial group of channels, with RN 8 two and a partial
    w20 = Weights.random(conv_layers=[[4, 3], [4, 3], [4, 3], [20, 3]], fc_layers=[20, 20, 20, 2], seed=6)
    # the device's default tiles, then small explicit ones: several tiles per
    # disparity with a partly empty last one, both work-item orders
    # the CPU-shaped conv kernel and fused head whatever the device's default (case network_wg has the others)
    cpu = dict(local_tiles=False, head_gemm=False)
    nets = [NetworkCost(ctx, w, **cpu),
            NetworkCost(ctx, w, tiles={"TM": 8, "RM": 2, "RN": 4, "ROWS_FASTEST": 1, "CONV_RM": 2}, **cpu),
            NetworkCost(ctx, w, tiles={"TM": 4, "RM": 1, "RN": 2, "ROWS_FASTEST": 0, "CONV_RM": 3}, **cpu),
            # 256 row groups x 8 column groups > Oclgrind's 1024 work-items:
            # fewer work-items than (row, column) groups, each walking several
            NetworkCost(ctx, w, tiles={"TM": 256, "RM": 1, "RN": 1, "ROWS_FASTEST": 0, "CONV_RM": 1}, **cpu),
            # the cpu rules column's tiles whatever the device (Oclgrind's gpu column has RN 4):
            # RN 16 (float vector width 16; the conv stack's RN too), RN 8 (width 8) with RM 4
            NetworkCost(ctx, w20, tiles={"TM": 64, "RM": 8, "RN": 16, "ROWS_FASTEST": 1, "CONV_RM": 4}, **cpu),
            NetworkCost(ctx, w20, tiles={"TM": 64, "RM": 4, "RN": 8, "ROWS_FASTEST": 1, "CONV_RM": 4}, **cpu)]
    sizes = ((12, 20, 5), (11, 13, 7), (12, 17, 5), (12, 15, 4),  # 2nd: D >= W (cropped W = 5)
             (12, 19, 5), (11, 16, 6))
    import mccnn_cl.costs.network as network_module

    for i, (net, (h, wd, D)) in enumerate(zip(nets, sizes, strict=True)):
        w = net.weights
        left, right = _images(rng, h, wd)
        H, W = h - 2 * w.margin, wd - 2 * w.margin
        out = _poisoned(ctx, D * H * W * 4)
        saved = network_module.BAND_BYTES, network_module.CHUNK_CELLS
        if i == 1:  # bands of one volume row, chunks of one disparity: seams and chunking
            network_module.BAND_BYTES, network_module.CHUNK_CELLS = 1, 1
        try:
            net(left, right, D, out=out)
        finally:
            network_module.BAND_BYTES, network_module.CHUNK_CELLS = saved
        got = ctx.from_device(out, (D, H, W))
        # float32 kernel vs float64 reference through 7 layers of 4-8 units:
        # rounding differences are ~1e-6 on costs in [0, 1]
        chk.close(f"C_CNN {h}x{wd} D={D} tiles {net.tm}/{net.rm}/{net.rn} hidden {net.hp} nwi {net.nwi}", got, ref.cost_volume(w, left, right, D), atol=2e-5, rtol=1e-4)


def case_fst(ctx, rng, chk):
    """fst.cl (normalisation, cosine volume) after the conv stack without its last ReLU."""
    from mccnn_cl.reference import network as ref
    from mccnn_cl.costs.fst import FstCost
    from mccnn_cl.weights import Weights

    w = Weights.random(conv_layers=[[6, 3], [5, 3]], architecture="mccnn-fst", seed=4)  # patch 5
    # the CPU-shaped kernels whatever the device's default (case fst_wg has the GPU-shaped ones):
    cost = FstCost(ctx, w, local_tiles=False, workgroup=False, volume_width=16)  # pairs of 16-pixel vectors
    cost8 = FstCost(ctx, w, local_tiles=False, workgroup=False, volume_width=8)  # pairs of 8-pixel vectors
    # 2nd: D >= W (cropped W = 9), 3rd: cropped width 35 (a partial 16-pixel block)
    for cost, (h, wd, D) in ((cost, (9, 21, 7)), (cost, (8, 13, 11)), (cost, (7, 39, 20)),
                             (cost8, (8, 13, 11)), (cost8, (7, 39, 20))):
        left, right = _images(rng, h, wd)
        H, W = h - 2 * w.margin, wd - 2 * w.margin
        out = _poisoned(ctx, D * H * W * 4)
        cost(left, right, D, out=out)
        # float32 dot products of 5 unit-vector components: ~1e-7
        chk.close(f"fst {h}x{wd} D={D} width {cost.volume_width}", ctx.from_device(out, (D, H, W)), ref.fst_cost_volume(w, left, right, D),
                  atol=2e-6, rtol=0)
    # the maps and planar features carved from a lent buffer (sub-buffers, StereoMatcher's
    # loan of SGM's volume): the same volume; the simulator checks every access against
    # each sub-buffer's own bounds
    cost.release_buffers()
    lent = _poisoned(ctx, sum(cost._pooled_scratch(H, W)) + 8 * ctx.sub_buffer_align)
    again = _poisoned(ctx, D * H * W * 4)
    cost(left, right, D, out=again, scratch=lent)
    chk.close(f"fst {h}x{wd} D={D}, maps in a lent buffer", ctx.from_device(again, (D, H, W)),
              ctx.from_device(out, (D, H, W)))


def case_winograd(ctx, rng, chk):
    """network_conv_wino.cl (the CPU column's 3 x 3 layers by Winograd's F(2x2, 3x3), forced
    here: Oclgrind takes the gpu column) in a conv stack at two register blocks: the features
    against the float64 tower, then a band cut at an odd row (the row anchor) against the
    whole image's rows bit for bit."""
    from mccnn_cl.reference import network as ref
    from mccnn_cl.costs.features import ConvStack, normalise
    from mccnn_cl.weights import Weights

    # two layers: the second (fst's last, no ReLU) by Winograd, the first (one channel) direct
    w = Weights.random(conv_layers=[[16, 3], [16, 3]], architecture="mccnn-fst", seed=6)
    raw = rng.random((13, 29)).astype(np.float32)
    img = normalise(raw)[:, :, None]
    r0, r1 = 3, 12

    def features(stack, rows, row0=0):
        H, W = rows.shape[:2]
        d = stack(ctx.to_device(np.ascontiguousarray(rows)), H, W, row0)
        h, wd = H - stack.patch + 1, W - stack.patch + 1
        return ctx.from_device(d, (h, wd, stack.stride))

    for rn, block in ((16, (4, 4)), (8, (3, 2))):
        stack = ConvStack(ctx, w, rn, 3, local_tiles=False, winograd=block)
        assert [l[0].wino for l in stack.layers] == [None, block]
        whole = features(stack, img)
        # float32 sums of 9 x 16 terms after a 9-term layer: ~1e-6 of features of magnitude ~1
        chk.close(f"conv stack with Winograd {block} RN {rn}", whole[:, :, :w.feature_maps],
                  ref.image_features(w, raw), atol=1e-5)
        band = features(stack, img[r0:r1], r0)
        chk.close(f"conv stack with Winograd {block} RN {rn}, rows {r0}..{r1}", band,
                  whole[r0:r1 - stack.patch + 1])


def case_acrt(ctx, rng, chk):
    """network_head.cl with the 1-output sigmoid layer (NOUT=1)."""
    from mccnn_cl.reference import network as ref
    from mccnn_cl.costs.network import AcrtCost
    from mccnn_cl.weights import Weights

    w = Weights.random(conv_layers=[[4, 3], [4, 3]], fc_layers=[8, 8, 1], architecture="mccnn-acrt", seed=5)
    for tiles, (h, wd, D) in ((None, (9, 17, 5)), ({"TM": 4, "RM": 2, "RN": 4, "ROWS_FASTEST": 0, "CONV_RM": 3},
                                                    (8, 11, 9)),
                              # the cpu rules column's tile whatever the device: RN 16 (hidden width padded to 16)
                              ({"TM": 64, "RM": 8, "RN": 16, "ROWS_FASTEST": 1, "CONV_RM": 4}, (9, 14, 5))):
        left, right = _images(rng, h, wd)
        H, W = h - 2 * w.margin, wd - 2 * w.margin
        out = _poisoned(ctx, D * H * W * 4)
        AcrtCost(ctx, w, tiles=tiles, local_tiles=False, head_gemm=False)(left, right, D, out=out)
        chk.close(f"acrt {h}x{wd} D={D}", ctx.from_device(out, (D, H, W)), ref.cost_volume(w, left, right, D),
                  atol=2e-5, rtol=1e-4)


def case_network_wg(ctx, rng, chk):
    """network_conv_wg.cl (the conv stack and the L4 split as a local-memory
    tiled GEMM) and network_head_wg.cl (the head layer by layer, its hidden
    layers that GEMM as 1 x 1 convolutions): the paper and acrt structures
    with the device's tile and forced ones of 15 to 30 work-items (partial
    tiles in pixels, channels and terms; sizes that are no powers of two; at
    most 32 work-items, Rusticl's limit), so that Oclgrind's race and barrier
    checks see the local blocks shared; runs of 13 cells (across rows), half
    storage; against the reference and, bit for bit, the CPU-shaped kernels
    (network_conv, the fused head) with the same register tiles."""
    import mccnn_cl.costs.network as network_module
    from mccnn_cl.reference import network as ref
    from mccnn_cl.costs.network import AcrtCost, PaperCost
    from mccnn_cl.weights import Weights

    paper = Weights.random(conv_layers=[[5, 3], [6, 3]], fc_layers=[8, 8, 8, 2], seed=3)
    acrt = Weights.random(conv_layers=[[4, 3], [7, 3]], fc_layers=[8, 8, 1], architecture="mccnn-acrt", seed=5)
    saved = network_module.GEMM_CELLS
    network_module.GEMM_CELLS = 13
    try:
        for cls, w, tile, (h, wd, D), half in (
                (PaperCost, paper, True, (9, 17, 5), False),
                (PaperCost, paper, dict(TM=6, TN=5, TK=4, RM=2, RN=1), (8, 13, 7), False),
                (AcrtCost, acrt, dict(TM=8, TN=8, TK=7, RM=2, RN=2), (9, 14, 5), False),
                (AcrtCost, acrt, dict(TM=10, TN=3, TK=3, RM=1, RN=1), (7, 11, 4), False),
                (PaperCost, paper, True, (8, 12, 4), True)):
            left, right = _images(rng, h, wd)
            H, W = h - 2 * w.margin, wd - 2 * w.margin
            vols = []
            tiles = {"RN": 4, "TM": 8, "RM": 2}  # the same register tiles (the last layer's RN) on both sides
            for lt, gemm in ((tile, True), (False, False)):
                if half:
                    out = ctx.empty(2 * D * H * W, "test output")
                    ctx.fill(out, -65504.0, 2 * D * H * W, np.float16)
                else:
                    out = _poisoned(ctx, D * H * W * 4)
                cls(ctx, w, tiles=tiles, half=half, local_tiles=lt, head_gemm=gemm)(left, right, D, out=out)
                vols.append(ctx.from_device(out, (D, H, W), np.float16 if half else np.float32))
            label = f"{cls.__name__} {h}x{wd} D={D} conv tile {tile} half={half}"
            chk.close(f"{label} vs reference", vols[0].astype(np.float32), ref.cost_volume(w, left, right, D),
                      atol=2e-5 + (2 ** -11 if half else 0.0), rtol=1e-4)
            chk.close(f"{label} = CPU-shaped conv and fused head", vols[0], vols[1])
    finally:
        network_module.GEMM_CELLS = saved


def case_fst_wg(ctx, rng, chk):
    """fst_wg.cl (the cosine volume with a work-group per column tile,
    disparity chunk and row, local-memory slices of the features) after the
    GEMM conv stack: the device's tile and forced ones of 4 to 30 work-items
    (partial tiles in columns, disparities and maps; whole tiles left of d;
    D >= W), half storage; against the reference and, bit for bit, the
    CPU-shaped kernels."""
    from mccnn_cl.reference import network as ref
    from mccnn_cl.costs.fst import FstCost
    from mccnn_cl.weights import Weights

    w = Weights.random(conv_layers=[[6, 3], [5, 3]], architecture="mccnn-fst", seed=4)  # patch 5, 5 maps
    for wg, lt, (h, wd, D), half in ((True, True, (7, 25, 9), False),
                                     (dict(TX=4, TD=4, TK=2, RX=2, RD=2), dict(TM=4, TN=4, TK=5, RM=1, RN=1),
                                      (6, 23, 13), False),
                                     (dict(TX=6, TD=5, TK=3, RX=1, RD=1), False, (8, 13, 11), False),
                                     (dict(TX=8, TD=4, TK=5, RX=2, RD=1), True, (6, 21, 7), True)):
        left, right = _images(rng, h, wd)
        H, W = h - 2 * w.margin, wd - 2 * w.margin
        vols = []
        for cost in (FstCost(ctx, w, half=half, local_tiles=lt, workgroup=wg),
                     FstCost(ctx, w, half=half, local_tiles=False, workgroup=False)):
            if half:
                out = ctx.empty(2 * D * H * W, "test output")
                ctx.fill(out, -65504.0, 2 * D * H * W, np.float16)
            else:
                out = _poisoned(ctx, D * H * W * 4)
            cost(left, right, D, out=out)
            vols.append(ctx.from_device(out, (D, H, W), np.float16 if half else np.float32))
        label = f"fst work-group {h}x{wd} D={D} volume tile {wg} conv tile {lt} half={half}"
        # float32: case fst's 2e-6; half: + half an ulp at 1 (2^-11)
        chk.close(f"{label} vs reference", vols[0].astype(np.float32), ref.fst_cost_volume(w, left, right, D),
                  atol=2e-6 + (2 ** -11 if half else 0.0))
        chk.close(f"{label} = CPU-shaped kernels", vols[0], vols[1])


def case_census(ctx, rng, chk):
    from mccnn_cl.reference import disparity as ref
    from mccnn_cl.costs.census import CensusCost

    # the device's launch shape, and the CPU-shaped one (all levels per work-item)
    for shape in (None, (0, (16, 1, 1))):
        st = CensusCost(ctx, launch_shape=shape)
        for (h, wd, D) in ((12, 20, 5), (11, 13, 7), (10, 43, 20)):
            left, right = _images(rng, h, wd)
            H, W = h - 8, wd - 8
            out = _poisoned(ctx, D * H * W * 4)
            st(left, right, D, out=out)
            # Hamming distance / 80: exact in float32
            chk.close(f"census {h}x{wd} D={D} shape {shape}", ctx.from_device(out, (D, H, W)),
                      ref.census_cost(left, right, D))


def case_range(ctx, rng, chk):
    """range.cl: the cost ceiling into a working frame's padding cells (mccnn_cl.disprange)."""
    from mccnn_cl.disprange import RangeMask, mask_reference

    for half in (False, True):
        st = RangeMask(ctx, half=half)
        for (D, H, W, lo, hi) in ((6, 3, 15, 4, 9), (5, 2, 7, 0, 3)):
            C = _volume(rng, D, H, W)
            if half:
                C = C.astype(np.float16)
            buf = ctx.empty(C.nbytes, "test volume")  # read-write (to_device's is read-only)
            ctx.cl.enqueue_copy(ctx.queue, buf, C)
            st(buf, D, H, W, lo, hi)
            chk.close(f"range mask D={D} {H}x{W} lo={lo} hi={hi} half={half}",
                      ctx.from_device(buf, (D, H, W), C.dtype), mask_reference(C, lo, hi))


def case_disparity(ctx, rng, chk):
    """disparity.cl (WTA left/right, LR check), interpolate.cl, subpixel.cl;
    the left WTA with 8 chunks per work-item and the mirroring with a
    work-item per line (the cpu rules column's forms) in float32 and half;
    and the working frame of a range with M < 0 (right_width < W, first_column > 0)."""
    from mccnn_cl.reference import disparity as ref
    from mccnn_cl.stages.disparity import Interpolate, LeftRightCheck, RightReference, Subpixel, WinnerTakeAll

    wta, lrc, itp, sub = WinnerTakeAll(ctx), LeftRightCheck(ctx), Interpolate(ctx), Subpixel(ctx)
    rr = RightReference(ctx)
    for (D, H, W) in ((5, 4, 13), (7, 3, 5)):
        C = _volume(rng, D, H, W)
        d_C = ctx.to_device(C)
        n = H * W * 4
        d_l, d_r, d_lab = _poisoned(ctx, n, np.int32), _poisoned(ctx, n, np.int32), _poisoned(ctx, n, np.int32)
        wta.left(d_C, D, H, W, out=d_l)
        wta.right(d_C, D, H, W, out=d_r)
        lrc(d_l, d_r, D, H, W, out=d_lab)
        DL, DR = ref.wta_left(C), ref.wta_right(C)
        chk.close(f"WTA left D={D} {H}x{W}", ctx.from_device(d_l, (H, W), np.int32), DL)
        chk.close(f"WTA right D={D} {H}x{W}", ctx.from_device(d_r, (H, W), np.int32), DR)
        # right reference: mirrored C_R (exact copy of cells), WTA on it, mirrored back
        d_crm = ctx.to_device(C, writable=True)
        rr.volume(d_crm, D, H, W)  # in place
        chk.close(f"right-reference volume D={D} {H}x{W}", ctx.from_device(d_crm, (D, H, W)),
                  ref.right_cost_volume(C)[:, :, ::-1])
        d_back = _poisoned(ctx, n, np.int32)
        rr.mirror(wta.left(d_crm, D, H, W), H, W, out=d_back)
        chk.close(f"mirrored WTA of C_R D={D} {H}x{W}", ctx.from_device(d_back, (H, W), np.int32), DR)
        lab = ref.lr_check(DL, DR, D)
        if (D, H, W) == (5, 4, 13):  # the mirroring's 16-cell path too (lines of >= 32 cells), there and back
            C2 = _volume(rng, 3, 2, 71)
            d_c2 = ctx.to_device(C2, writable=True)
            rr.volume(d_c2, 3, 2, 71)
            chk.close("right-reference volume D=3 2x71", ctx.from_device(d_c2, (3, 2, 71)),
                      ref.right_cost_volume(C2)[:, :, ::-1])
            rr.volume(d_c2, 3, 2, 71)
            chk.close("right-reference volume back D=3 2x71", ctx.from_device(d_c2, (3, 2, 71)), C2)
        chk.close(f"LR check D={D} {H}x{W}", ctx.from_device(d_lab, (H, W), np.int32), lab)
        for directions in ("paper", "code"):
            d_int = _poisoned(ctx, n, np.int32)
            itp(d_l, d_lab, H, W, directions=directions, out=d_int)
            want = ref.interpolate(DL, lab, directions=directions, stop_at_any=directions == "code")
            chk.close(f"interpolate {directions} {H}x{W}", ctx.from_device(d_int, (H, W), np.int32), want)
        for mind, clamp in ((0.0, False), (1e-5, True)):
            d_se = _poisoned(ctx, n)
            sub(d_C, d_l, D, H, W, min_denominator=mind, clamp_step=clamp, out=d_se)
            # one division of float32 differences: a few ulps of d
            chk.close(f"subpixel {mind} {clamp} {H}x{W}", ctx.from_device(d_se, (H, W)),
                      ref.subpixel(C, DL, min_denominator=mind, clamp_step=clamp), atol=1e-5, rtol=1e-5)

    # the cpu rules column's forms whatever the device's (Oclgrind takes the gpu column's: a
    # 16-pixel chunk per WTA work-item, a work-item per 16-pair block of the mirroring): 8
    # chunks per work-item (W = 150: a whole 128-pixel span and a partial one) and a work-item
    # per (d, y) line, there and back, in float32 and half
    for half in (False, True):
        wta8, rr_lines = WinnerTakeAll(ctx, half=half, chunks=8), RightReference(ctx, half=half, lines=True)
        for (D, H, W) in ((5, 4, 13), (3, 2, 150)):
            C = _volume(rng, D, H, W).astype(np.float16 if half else np.float32)
            C32 = C.astype(np.float32)
            d_l = _poisoned(ctx, H * W * 4, np.int32)
            wta8.left(ctx.to_device(C), D, H, W, out=d_l)
            chk.close(f"WTA left, 8 chunks per work-item, D={D} {H}x{W} half={half}",
                      ctx.from_device(d_l, (H, W), np.int32), ref.wta_left(C32))
            d_v = ctx.to_device(C, writable=True)
            rr_lines.volume(d_v, D, H, W)
            chk.close(f"right-reference volume, a work-item per line, D={D} {H}x{W} half={half}",
                      ctx.from_device(d_v, (D, H, W), C.dtype), ref.right_cost_volume(C32)[:, :, ::-1].astype(C.dtype))
            rr_lines.volume(d_v, D, H, W)
            chk.close(f"right-reference volume back, a work-item per line, D={D} {H}x{W} half={half}",
                      ctx.from_device(d_v, (D, H, W), C.dtype), C)

    # the working frame of a range with M < 0 (pipeline._volume_stages): the left image's real
    # columns from lo, the right's up to Wr = W - lo; the check takes no candidate whose right
    # pixel is padding, interpolation walks end at lo, the subpixel fit keeps d where a cell
    # compares with padding.  Each reference must differ from the full frame's (else the
    # input no longer reaches the path).
    for (D, H, W), lo in (((5, 4, 13), 3), ((7, 3, 11), 4)):
        Wr, n = W - lo, H * W * 4
        C = _volume(rng, D, H, W)
        d_C = ctx.to_device(C)
        DL, DR = ref.wta_left(C).astype(np.int32), ref.wta_right(C).astype(np.int32)
        d_l = ctx.to_device(DL)
        d_lab = _poisoned(ctx, n, np.int32)
        lrc(d_l, ctx.to_device(DR), D, H, W, out=d_lab, right_width=Wr)
        lab = ref.lr_check(DL, DR, D, right_width=Wr)
        label = f"D={D} {H}x{W} right_width={Wr} first_column={lo}"
        chk.close(f"LR check {label}", ctx.from_device(d_lab, (H, W), np.int32), lab)
        chk.differs(f"LR check {label}: the range changes the labels", lab, ref.lr_check(DL, DR, D))
        d_lab_ref = ctx.to_device(lab)
        for directions in ("paper", "code"):
            d_int = _poisoned(ctx, n, np.int32)
            itp(d_l, d_lab_ref, H, W, directions=directions, out=d_int, first_column=lo)
            want = ref.interpolate(DL, lab, directions=directions, stop_at_any=directions == "code", first_column=lo)
            chk.close(f"interpolate {directions} {label}", ctx.from_device(d_int, (H, W), np.int32), want)
            chk.differs(f"interpolate {directions} {label}: the range changes the map", want,
                        ref.interpolate(DL, lab, directions=directions, stop_at_any=directions == "code"))
        DINT = want  # the code directions' map, as the pipeline's next input
        d_dint = ctx.to_device(DINT.astype(np.int32))
        for mind, clamp in ((0.0, False), (1e-5, True)):
            d_se = _poisoned(ctx, n)
            sub(d_C, d_dint, D, H, W, min_denominator=mind, clamp_step=clamp, out=d_se, right_width=Wr)
            want = ref.subpixel(C, DINT, min_denominator=mind, clamp_step=clamp, right_width=Wr)
            chk.close(f"subpixel {mind} {clamp} {label}", ctx.from_device(d_se, (H, W)), want, atol=1e-5, rtol=1e-5)
            chk.differs(f"subpixel {mind} {clamp} {label}: the range changes the map", want,
                        ref.subpixel(C, DINT, min_denominator=mind, clamp_step=clamp))


def case_confidence(ctx, rng, chk):
    """confidence.cl: the LR labels of the volume and all-correct labels, a
    D >= W volume, quantised costs (plateaus), an fst-like floor; float32 and
    half; the working frame of a range with M < 0 (right_width < W,
    first_column > 0), whose reference must differ from the full frame's."""
    from mccnn_cl.reference import confidence as ref
    from mccnn_cl.reference import disparity as dref
    from mccnn_cl.stages.confidence import Confidence

    for (D, H, W), levels, floor, half, lo in (((5, 4, 13), None, 0.0, False, 0), ((7, 3, 5), 3, 0.0, False, 0),
                                               ((6, 3, 11), 4, -1.0, False, 0), ((5, 4, 13), None, 0.0, True, 0),
                                               # M < 0: left padding columns 0 .. lo-1, right image W - lo wide
                                               ((5, 4, 13), None, 0.0, False, 3), ((6, 3, 11), 4, -1.0, True, 2)):
        Wr = W - lo
        C = _volume(rng, D, H, W)
        if levels:
            C = (np.floor(C * levels) / levels).astype(np.float32)
        if floor:
            C = C * 2 - 1
        if half:
            C = C.astype(np.float16)
        lab = dref.lr_check(dref.wta_left(C.astype(np.float32)), dref.wta_right(C.astype(np.float32)), D,
                            right_width=Wr)
        for name, labels in (("LR labels", lab), ("all correct", np.zeros((H, W), np.int32))):
            out = _poisoned(ctx, H * W * 4)
            rng_kw = dict(right_width=Wr, first_column=lo) if lo else {}  # lo = 0: the stage's defaults
            Confidence(ctx, half=half)(ctx.to_device(C), ctx.to_device(labels), D, H, W, floor, out=out, **rng_kw)
            want = ref.confidence(C, labels, floor, **rng_kw)
            label = f"confidence D={D} {H}x{W} levels={levels} floor={floor} half={half} {name}"
            if lo:
                label += f" right_width={Wr} first_column={lo}"
                chk.differs(f"{label}: the range changes the map", want, ref.confidence(C, labels, floor))
            # one float32 division, rounded within 2.5 ulp by OpenCL: < 3e-7 on values <= 1
            chk.close(label, ctx.from_device(out, (H, W)), want, atol=1e-6)


def case_refine(ctx, rng, chk):
    """refine.cl: enlarge, median, bilateral."""
    from mccnn_cl.reference import disparity as ref
    from mccnn_cl.stages.refine import BilateralFilter, Enlarge, MedianFilter

    H, W, m = 4, 29, 4  # 37 columns: the bilateral kernel has an interior 16-px chunk at radius 3
    Ho, Wo = H + 2 * m, W + 2 * m
    Dm = (rng.random((H, W)) * 5).astype(np.float32)
    d_D = ctx.to_device(Dm)
    d_big = _poisoned(ctx, Ho * Wo * 4)
    Enlarge(ctx)(d_D, H, W, Ho, Wo, m, out=d_big)
    big = ref.enlarge(Dm, m, (Ho, Wo))
    chk.close("enlarge", ctx.from_device(d_big, (Ho, Wo)), big)
    d_med = _poisoned(ctx, Ho * Wo * 4)
    MedianFilter(ctx, 5)(d_big, Ho, Wo, out=d_med)
    med = ref.median_filter(big, 5)
    chk.close("median 5", ctx.from_device(d_med, (Ho, Wo)), med)
    d_med3 = _poisoned(ctx, Ho * Wo * 4)
    MedianFilter(ctx, 3, vector=False)(d_big, Ho, Wo, out=d_med3)  # the sorting kernel
    chk.close("median 3 (sorting)", ctx.from_device(d_med3, (Ho, Wo)), ref.median_filter(big, 3))
    guide = rng.random((Ho, Wo)).astype(np.float32)
    d_bf = _poisoned(ctx, Ho * Wo * 4)
    BilateralFilter(ctx)(d_med, ctx.to_device(guide), Ho, Wo, sigma=2.0, tau=0.3, radius=3, out=d_bf)
    # weighted mean of <= 49 float32 terms: relative rounding ~1e-6
    chk.close("bilateral", ctx.from_device(d_bf, (Ho, Wo)),
              ref.bilateral(med, guide, 2.0, 3, 0.3), atol=1e-5, rtol=1e-5)


def _blocky(rng, H, W, block=3):
    """Piecewise-constant image plus a little noise: arms of varied lengths."""
    base = rng.random((H // block + 1, W // block + 1))
    img = np.kron(base, np.ones((block, block)))[:H, :W] + 0.02 * rng.random((H, W))
    return np.clip(img, 0, 1).astype(np.float32)


def case_cross(ctx, rng, chk):
    """cross.cl: arms of both variants (paper, released code's include_neighbor)."""
    from mccnn_cl.reference.aggregation import cross_arms
    from mccnn_cl.stages.cross import CrossArms, arms_from_device

    st = CrossArms(ctx)
    for (H, W), kw in (((4, 13), {}), ((5, 7), {"eta": 9, "include_neighbor": True}), ((1, 6), {})):
        img = _blocky(rng, H, W)
        out = _poisoned(ctx, 4 * H * W, np.int32)  # uchar4 per pixel: poison as int32 words
        st(ctx.to_device(img), H, W, out=out, **kw)
        chk.close(f"arms {H}x{W} {kw}", arms_from_device(ctx, out, H, W), cross_arms(img, **kw))


def case_cbca(ctx, rng, chk):
    """cbca.cl: multi-iteration fused kernel (several iterations per launch
    and a shorter last launch, out of place and in place), one-iteration fused
    kernel (out of place and in place), rows + columns passes; arms from the
    CrossArms stage.  The multi kernel in both forms of a masked term
    (CBCA_SELECT_ADD 0: one masked add, CPUs with AVX-512; 1: the mask on the
    term, other CPUs), whatever the device's."""
    from mccnn_cl.reference.aggregation import cbca, cross_arms
    from mccnn_cl.stages.cbca import CBCA
    from mccnn_cl.stages.cross import CrossArms, max_arm

    for (D, H, W), eta, bound, fused, multi, it, in_place, select_add in (
            ((5, 4, 13), 4, max_arm(4), False, False, 2, False, None),
            ((7, 5, 5), 9, 255, False, False, 2, False, None),
            ((4, 3, 40), 4, max_arm(4), True, False, 2, False, None),
            ((3, 5, 21), 4, max_arm(4), True, False, 2, True, None),
            ((4, 9, 35), 4, max_arm(4), True, True, 5, False, False),
            ((4, 9, 35), 4, max_arm(4), True, True, 5, False, True),
            ((19, 6, 21), 9, max_arm(9), True, True, 2, True, False),
            ((19, 6, 21), 9, max_arm(9), True, True, 2, True, True)):
        img_l, img_r = _blocky(rng, H, W), _blocky(rng, H, W)
        C = _volume(rng, D, H, W)
        d_al = CrossArms(ctx)(ctx.to_device(img_l), H, W, eta=eta)
        d_ar = CrossArms(ctx)(ctx.to_device(img_r), H, W, eta=eta)
        if in_place:
            out = ctx.empty(C.nbytes, "test in-place volume")
            ctx.cl.enqueue_copy(ctx.queue, out, C)
            src = out
        else:
            out = _poisoned(ctx, 4 * D * H * W)
            src = ctx.to_device(C)
        CBCA(ctx, max_arm=bound, fused=fused, multi=multi, select_add=select_add)(
            src, d_al, d_ar, D, H, W, iterations=it, max_arm=bound, out=out)
        want = cbca(C, cross_arms(img_l, eta=eta), cross_arms(img_r, eta=eta), it)
        # means of <= 81 float32 costs in [0, 1] with compensated sums: the
        # stage's own tests use 1e-5 of the cost range
        chk.close(f"CBCA D={D} {H}x{W} eta={eta} fused={fused} multi={multi} iterations={it} in_place={in_place}"
                  f"{'' if select_add is None else f' select_add={select_add}'}",
                  ctx.from_device(out, (D, H, W)), want, atol=1e-5)


def case_cbca_wg(ctx, rng, chk):
    """cbca_wg.cl (CBCA's work-group path: a group per row / column tile and
    disparity, rings in local memory, two barriers per chunk): groups of
    several work-items (rows 3 to 8; column tiles 2 x 2 to 8 x 2, shapes that
    do not divide W or H), several chunks per line, in place and out of
    place, arms up to 8, half storage; so that Oclgrind's race and barrier
    checks see the local memory shared."""
    from mccnn_cl.reference.aggregation import cbca, cross_arms
    from mccnn_cl.stages.cbca import CBCA
    from mccnn_cl.stages.cross import CrossArms, max_arm

    for (D, H, W), eta, nb, ls, it, in_place, half in (
            ((5, 4, 13), 4, False, (4, (3, 2)), 2, False, False),
            ((4, 7, 9), 4, False, (3, (2, 3)), 1, True, False),
            ((3, 6, 21), 9, True, (8, (8, 2)), 1, False, False),
            ((4, 5, 11), 4, False, (5, (2, 2)), 2, True, True)):
        img_l, img_r = _blocky(rng, H, W), _blocky(rng, H, W)
        C = _volume(rng, D, H, W)
        if half:
            C = C.astype(np.float16)
        d_al = CrossArms(ctx)(ctx.to_device(img_l), H, W, eta=eta, include_neighbor=nb)
        d_ar = CrossArms(ctx)(ctx.to_device(img_r), H, W, eta=eta, include_neighbor=nb)
        if in_place:
            out = ctx.empty(C.nbytes, "test in-place volume")
            ctx.cl.enqueue_copy(ctx.queue, out, C)
            src = out
        else:
            if half:
                out = ctx.empty(C.nbytes, "test output")
                ctx.fill(out, -65504.0, C.nbytes, np.float16)
            else:
                out = _poisoned(ctx, C.nbytes)
            src = ctx.to_device(C)
        bound = max_arm(eta, nb)
        st = CBCA(ctx, max_arm=bound, workgroup=True, local_size=ls, half=half)
        assert st.path(bound) == "workgroup"
        st(src, d_al, d_ar, D, H, W, iterations=it, max_arm=bound, out=out)
        got = ctx.from_device(out, (D, H, W), np.float16 if half else np.float32).astype(np.float32)
        want = cbca(C.astype(np.float32), cross_arms(img_l, eta=eta, include_neighbor=nb),
                    cross_arms(img_r, eta=eta, include_neighbor=nb), it)
        # float32: tests/test_cbca.py's 1e-5 of the cost range; half: tests/test_half.py's
        # 2 x iterations x 2^-11 relative (costs < 1)
        chk.close(f"CBCA work-group D={D} {H}x{W} eta={eta} nb={nb} local={ls} iterations={it} "
                  f"in_place={in_place} half={half}", got, want,
                  atol=1e-7 if half else 1e-5, rtol=2 * it * 2 ** -11 if half else 0.0)


def case_sgm(ctx, rng, chk):
    """sgm.cl: the four directions (rows and columns kernels), both penalty
    variants; the default configuration of this device and the CPU one (128
    columns per sgm_columns work-item, a partial strip; both row directions
    in one launch) with the first sweep in bands of rows (the vertical path's
    state carried between launches); the column kernel with and without its
    specialised row loops; with D >= 16 the row kernel's whole-tile path
    and the general path alone (SGM_WHOLE_TILES=0); the paired sweeps, in
    float32 and half; both on 8-wide vectors; the paired sweeps in 16-bit
    lanes."""
    from mccnn_cl.reference.aggregation import sgm
    from mccnn_cl.stages.sgm import SGM

    for (D, H, W), kw, cfg, half in (((5, 4, 13), {}, {}, False),
                                     ((7, 5, 5), {"variant": "code", "outside_large": False}, {}, False),
                                     ((5, 1, 19), {}, {"specialize": False}, False),
                                     ((6, 5, 21), {}, {"cols": 128, "band": 2, "fused_rows": True}, False),
                                     # D >= 16 and 16-column chunks: sgm_rows' whole-tile path (default off Rusticl)
                                     ((20, 3, 40), {}, {"fused_rows": True, "paired": False}, False),
                                     # ... and without it (SGM_WHOLE_TILES=0: the general path for every tile)
                                     ((20, 3, 40), {}, {"fused_rows": True, "paired": False, "whole_tiles": False},
                                      False),
                                     # the paired sweeps (default on CPUs with <= 2 compute units): odd H,
                                     # whole tiles and partial ones, a partial last chunk
                                     ((20, 5, 37), {}, {"paired": True}, False),
                                     ((7, 4, 9), {"variant": "code", "outside_large": False}, {"paired": True}, False),
                                     # 8-wide vectors (SGM_VW 8, the rule where a CPU's vectors hold 8 floats)
                                     ((20, 5, 37), {}, {"paired": True, "width": 8}, False),
                                     ((20, 3, 21), {}, {"paired": False, "width": 8, "cols": 32, "band": 2}, False),
                                     # half storage in the paired sweeps (a CPU's half volume: 8-wide
                                     # vectors, whole tiles)
                                     ((20, 5, 37), {}, {"paired": True, "width": 8}, True)):
        img_l, img_r = _blocky(rng, H, W), _blocky(rng, H, W)
        C, out = _volume_and_output(ctx, _volume(rng, D, H, W), half)
        SGM(ctx, half=half, **cfg)(ctx.to_device(C), ctx.to_device(img_l), ctx.to_device(img_r), D, H, W, out=out,
                                   **kw)
        got = ctx.from_device(out, (D, H, W), np.float16 if half else np.float32).astype(np.float32)
        # as tests/test_sgm.py: 2e-5 of (cost range + Pi2); float32 path sums re-based every step;
        # half (the reference on the half input): tests/test_half.py's half_sgm_bound, at most
        # 4 roundings to half (2^-11 relative each) of the result, + float32 arithmetic
        tol = dict(atol=2 ** -23, rtol=4 * 2 ** -11 + 2 ** -20) if half else dict(atol=2e-5 * (1.0 + 32.0))
        chk.close(f"SGM D={D} {H}x{W} {kw} {cfg} half={half}", got, sgm(C.astype(np.float32), img_l, img_r, **kw),
                  **tol)
    # the paired sweeps reading C as the right-reference volume C_R' (mirror=True: the pipeline's
    # right reference where SGM is paired): whole tiles, the diagonal ones (x0 < d) and the partial
    # last chunk read backwards along C's lines; against the reference on C_R' made in numpy
    from mccnn_cl.reference.disparity import right_cost_volume

    for (D, H, W), width, half in (((20, 5, 37), 8, False), ((20, 5, 37), 16, False), ((20, 5, 37), 8, True),
                                   ((9, 3, 8), 8, False)):
        img_l, img_r = _blocky(rng, H, W), _blocky(rng, H, W)
        C, out = _volume_and_output(ctx, _volume(rng, D, H, W), half)
        SGM(ctx, half=half, paired=True, width=width)(ctx.to_device(C), ctx.to_device(img_l), ctx.to_device(img_r),
                                                      D, H, W, out=out, mirror=True)
        got = ctx.from_device(out, (D, H, W), np.float16 if half else np.float32).astype(np.float32)
        mirrored = np.ascontiguousarray(right_cost_volume(C.astype(np.float32))[:, :, ::-1])
        tol = dict(atol=2 ** -23, rtol=4 * 2 ** -11 + 2 ** -20) if half else dict(atol=2e-5 * (1.0 + 32.0))
        chk.close(f"SGM mirror=True D={D} {H}x{W} width={width} half={half}", got, sgm(mirrored, img_l, img_r),
                  **tol)
    # the 16-bit sweeps (a call with cost_bound: sgm_paired_q16), plain and reading C mirrored: exactly
    # float SGM of the costs and penalties rounded to steps of 1 / s (tests/test_sgm_q16.py)
    from mccnn_cl.reference.aggregation import sgm_q16

    for (D, H, W), mirror in (((20, 5, 37), False), ((20, 5, 37), True), ((9, 3, 8), True)):
        img_l, img_r = _blocky(rng, H, W), _blocky(rng, H, W)
        C, out = _volume_and_output(ctx, _volume(rng, D, H, W), False)
        # Oclgrind (a "gpu" in the rules) runs them too; Mesa's llvmpipe, which aborts building them, not
        stage = SGM(ctx, paired=True, int16=ctx.profile.kind != "llvmpipe")
        stage(ctx.to_device(C), ctx.to_device(img_l), ctx.to_device(img_r), D, H, W, out=out, mirror=mirror,
              cost_bound=1.0)
        s = stage.last_scale
        got = ctx.from_device(out, (D, H, W))
        src = np.ascontiguousarray(right_cost_volume(C)[:, :, ::-1]) if mirror else C
        if s is None:  # the float sweeps
            chk.close(f"SGM (16-bit not taken) mirror={mirror} D={D} {H}x{W}", got, sgm(src, img_l, img_r),
                      atol=2e-5 * (1.0 + 32.0))
            continue
        chk.close(f"SGM 16-bit mirror={mirror} D={D} {H}x{W} s={s}", got, sgm_q16(src, img_l, img_r, 1.0, s))


def case_sgm_wg(ctx, rng, chk):
    """sgm_wg.cl (one work-group per path line, levels across its work-items,
    local-memory tree reduction with barriers): work-groups of 4, 16 and 5
    work-items (levels several per work-item, fewer levels than work-items,
    a group size that is not a power of two) so that Oclgrind's race and
    barrier checks see the local memory shared; float32 and half; and the
    vertical paths with 8, 16 and 32 columns per work-group (sgm_wg_cols)."""
    from mccnn_cl.reference.aggregation import sgm
    from mccnn_cl.stages.sgm_wg import SGMWorkGroup

    for (D, H, W), kw, L, half, cols in (((9, 4, 13), {}, 4, False, 0),
                                         ((7, 5, 6), {"variant": "code", "outside_large": False}, 16, False, 0),
                                         ((11, 3, 14), {}, 5, False, 0),
                                         ((6, 4, 9), {}, 4, True, 0),
                                         ((9, 5, 11), {}, 4, False, 8),   # sgm_wg_cols: 2 groups of 8 x 9
                                         ((6, 4, 9), {}, 4, True, 8),
                                         # the tuner's other widths: 16 (2 groups, the 2nd partial)
                                         # and 32 columns per group (a whole group and a partial one)
                                         ((9, 4, 21), {}, 4, False, 16),
                                         ((5, 3, 35), {}, 8, True, 32)):
        img_l, img_r = _blocky(rng, H, W), _blocky(rng, H, W)
        C, out = _volume_and_output(ctx, _volume(rng, D, H, W), half)
        SGMWorkGroup(ctx, half=half, local_size=L, cols=cols)(ctx.to_device(C), ctx.to_device(img_l),
                                                              ctx.to_device(img_r), D, H, W, out=out, **kw)
        got = ctx.from_device(out, (D, H, W), np.float16 if half else np.float32).astype(np.float32)
        # float32: as tests/test_sgm_wg.py; half: the four partial sums rounded
        # to half in place (tests/test_half.py's bound, costs < 1 + 4 P2)
        atol = 7 * 2 ** -11 * (1.0 + 4 * 32.0) if half else 2e-5 * (1.0 + 32.0)
        chk.close(f"SGM work-group D={D} {H}x{W} L={L} half={half} cols={cols} {kw}", got,
                  sgm(C.astype(np.float32), img_l, img_r, **kw), atol=atol)


def case_half(ctx, rng, chk):
    """Half-precision volume storage (VOL_HALF=1) in every kernel that reads or
    writes a volume: the network head and its NaN marking, then the whole
    method (census cost) with fused and with two-pass CBCA and with both SGM
    stages (SGM, SGMWorkGroup), against the same runs in float32 (the storage
    rounds to 11 significant bits)."""
    from mccnn_cl.pipeline import StereoMatcher
    from mccnn_cl.costs.network import NetworkCost
    from mccnn_cl.stages.sgm import SGM
    from mccnn_cl.stages.sgm_wg import SGMWorkGroup
    from mccnn_cl.weights import Weights

    w = Weights.random(conv_layers=[[4, 3], [4, 3], [4, 3], [4, 3]], fc_layers=[8, 8, 8, 2], seed=3)
    left, right = _images(rng, 12, 20)
    H, W, D = 12 - 2 * w.margin, 20 - 2 * w.margin, 5
    full = NetworkCost(ctx, w, head_gemm=False).compute(left, right, D)  # the fused head (network_wg: the other)
    out = ctx.empty(D * H * W * 2, "half volume")
    ctx.fill(out, -65504.0, D * H * W * 2, np.float16)
    NetworkCost(ctx, w, half=True, head_gemm=False)(left, right, D, out=out)
    chk.close("C_CNN half = float32 C_CNN rounded", ctx.from_device(out, (D, H, W), np.float16),
              full.astype(np.float16))
    left, right = _images(rng, 14, 24)
    ref = StereoMatcher(cost="census", max_disparity=D, device=ctx).compute(left, right, return_intermediates=True)
    # the device's SGM stage (make_sgm), then each SGM stage explicitly, whatever the device:
    # SGM's one-direction kernels (sgm_rows, sgm_columns; paired=False: a CPU with <= 2 compute
    # units would pick the paired sweeps, case sgm's) and the work-group stage
    for (fused, multi), sgm_stage in (((True, True), None), ((True, False), SGM), ((False, False), SGMWorkGroup)):
        m = StereoMatcher(cost="census", max_disparity=D, device=ctx, volume_dtype="float16")
        m.cbca.fused, m.cbca.multi = fused, multi
        m.cbca.workgroup = False  # the CPU paths (Oclgrind's default, "workgroup", is case cbca_wg's)
        if sgm_stage is SGM:
            m.sgm = SGM(ctx, half=True, paired=False)
        elif sgm_stage is not None:
            m.sgm = sgm_stage(ctx, half=True)
        label = f"fused={fused}, multi={multi}, {type(m.sgm).__name__}"
        got = m.compute(left, right, return_intermediates=True)
        chk.close(f"half census volume ({label})", got.intermediates["C_CNN"],
                  ref.intermediates["C_CNN"].astype(np.float16))
        for name in ("C_CBCA", "C_SGM", "C", "C_R"):  # a few half roundings per stage
            chk.close(f"half {name} ({label})", got.intermediates[name].astype(np.float32),
                      ref.intermediates[name], atol=1e-3, rtol=4e-3)
        chk.close(f"half D_BF ({label})", got.disparity, ref.disparity, atol=0.5)


def selftest_bad_kernel(ctx, rng, chk):
    """NOT a stage: a kernel with an out-of-bounds read and a local-memory race,
    to prove the harness fails when Oclgrind finds something."""
    src = """
    __kernel void bad(__global const float *a, __global float *b, int n) {
        __local float t[1];
        const int i = get_global_id(0);
        t[0] = a[i + 1];                     /* reads a[n]: out of bounds */
        barrier(CLK_LOCAL_MEM_FENCE);
        if (i < n) b[i] = t[0];
    }"""
    prg = ctx.cl.Program(ctx.context, src).build()
    n = 8
    d_a, d_b = ctx.to_device(np.arange(n, dtype=np.float32)), ctx.empty(n * 4)
    prg.bad(ctx.queue, (n,), (n,), d_a, d_b, np.int32(n))
    chk.close("bad kernel ran", ctx.from_device(d_b, (n,)).shape, (n,))


# Stages covered: add a case here once its stage is committed.
CASES = {
    "network": case_network,
    "network_wg": case_network_wg,
    "fst": case_fst,
    "fst_wg": case_fst_wg,
    "winograd": case_winograd,
    "acrt": case_acrt,
    "census": case_census,
    "range": case_range,
    "cross": case_cross,
    "cbca": case_cbca,
    "cbca_wg": case_cbca_wg,
    "sgm": case_sgm,
    "sgm_wg": case_sgm_wg,
    "disparity": case_disparity,
    "refine": case_refine,
    "half": case_half,
    "confidence": case_confidence,
}
SELFTESTS = {"selftest_bad_kernel": selftest_bad_kernel}
# everything the worker can run by name (cases of stages not committed yet included)
RUNNABLE = {**{n[5:]: f for n, f in globals().items() if n.startswith("case_")}, **SELFTESTS}


# ---------------------------------------------------------------------------
# worker (subprocess) entry point
# ---------------------------------------------------------------------------
def run_case(name: str, expect_platform: str | None) -> dict:
    from mccnn_cl.opencl.context import ClContext

    ctx = ClContext()
    plat = ctx.device.platform.name.strip()
    if expect_platform and expect_platform.lower() not in plat.lower():
        return {"case": name, "ok": False, "error": f"runs on {plat!r}, expected {expect_platform!r}"}
    chk = Checks()
    fetched = set()
    forms = []
    plain_kernel = ctx.kernel

    def kernel(filename, kname, **defines):  # records which kernels the stages fetch, and their build options
        fetched.add(kname)
        forms.append((kname, defines))
        return plain_kernel(filename, kname, **defines)

    ctx.kernel = kernel
    t0 = time.perf_counter()
    RUNNABLE[name](ctx, np.random.default_rng(1234), chk)
    ctx.finish()
    missing = sorted(CASE_KERNELS.get(name, set()) - fetched - NOT_BUILT_ON.get(ctx.profile.kind, set()))
    if missing:
        chk.results.append({"name": f"kernels not fetched: {missing}", "ok": False, "shape": [], "err": None})
    absent = [f"{k} {want}" for k, want in CASE_FORMS.get(name, ())
              if not any(fk == k and all(k2 in fd and fd[k2] == v for k2, v in want.items()) for fk, fd in forms)]
    if absent:
        chk.results.append({"name": f"kernel forms not fetched: {absent}", "ok": False, "shape": [], "err": None})
    return {"case": name, "ok": not chk.failures, "device": ctx.describe(),
            "seconds": round(time.perf_counter() - t0, 2), "checks": chk.results,
            "kernels": sorted(fetched)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("cases", nargs="*", help=f"cases to run ({', '.join(CASES)})")
    ap.add_argument("--all", action="store_true", help="run every case")
    ap.add_argument("--expect-platform", help="fail unless the context's platform name contains this")
    ap.add_argument("--impl", help="re-run self in a subprocess on this implementation "
                    "(pocl, intel, oclgrind, rusticl; see tests/conftest.py)")
    args = ap.parse_args(argv)
    names = list(CASES) if args.all else args.cases
    if not names:
        ap.error("name cases or --all")
    if args.impl:
        rc = 0
        for name in names:
            res = run_isolated(args.impl, name)
            print(json.dumps(res["result"], indent=1) if res["result"] else res["stderr"][-4000:])
            if res["oclgrind_errors"]:
                print(res["oclgrind_errors"][:8000])
            rc |= 0 if res["ok"] else 1
        return rc
    rc = 0
    for name in names:
        res = run_case(name, args.expect_platform)
        print("RESULT " + json.dumps(res), flush=True)
        rc |= 0 if res["ok"] else 1
    return rc


# ---------------------------------------------------------------------------
# the pytest side
# ---------------------------------------------------------------------------
try:
    import pytest
except ImportError:  # the worker needs no pytest
    pytest = None

if pytest is not None:

    @pytest.fixture(scope="module")
    def oclgrind_available():
        from conftest import ImplUnavailable, icd_file

        try:
            return icd_file("oclgrind")
        except ImplUnavailable as exc:
            pytest.fail(f"Oclgrind is needed for these tests: {exc}")

    @pytest.mark.oclgrind
    @pytest.mark.parametrize("case", sorted(CASES))
    def test_stage_under_oclgrind(case, oclgrind_available):
        res = run_isolated("oclgrind", case, timeout=300)
        print(f"{case}: {res['seconds']:.1f} s under Oclgrind")
        if res["oclgrind_errors"]:
            pytest.fail(f"Oclgrind reported errors for {case}:\n{res['oclgrind_errors'][:20000]}")
        if res["result"] is None or res["returncode"] != 0 and not res["result"]:
            pytest.fail(f"worker for {case} failed (rc {res['returncode']}):\n{res['stderr'][-6000:]}")
        bad = [r for r in res["result"].get("checks", []) if not r["ok"]]
        assert res["result"]["ok"] and not bad, f"{case}: kernel != reference under Oclgrind: {bad or res['result']}"
        assert res["result"]["checks"], f"{case} compared nothing"

    def test_oclgrind_harness_catches_a_bad_kernel(oclgrind_available):
        """The subprocess + log check really fails on an out-of-bounds read and a race."""
        res = run_isolated("oclgrind", "selftest_bad_kernel", timeout=120)
        assert res["result"] is not None and res["result"]["ok"], res["stderr"][-3000:]
        assert not res["ok"]
        assert "Invalid read" in res["oclgrind_errors"], res["oclgrind_errors"][:3000]
        assert "data race" in res["oclgrind_errors"], res["oclgrind_errors"][:3000]

    def test_every_kernel_is_covered():
        """Every kernel of kernels/*.cl that the package fetches by name is in some case."""
        import re

        repo = HERE.parent
        defined = {}
        for cl_file in sorted((repo / "mccnn_cl" / "kernels").glob("*.cl")):
            for k in re.findall(r"__kernel\s+void\s+(\w+)", cl_file.read_text(encoding="utf-8")):
                defined[k] = cl_file.name
        used_text = "\n".join(p.read_text(encoding="utf-8") for p in sorted((repo / "mccnn_cl").rglob("*.py")))
        used = {k for k in defined if re.search(rf"[\"']{k}[\"']", used_text)}
        assert set(CASE_KERNELS) == set(CASES), "helpers.CASE_KERNELS and CASES name different cases"
        assert set(CASE_FORMS) <= set(CASES), "helpers.CASE_FORMS names a case not in CASES"
        assert all(k in CASE_KERNELS[c] for c in CASE_FORMS for k, _ in CASE_FORMS[c]), \
            "a kernel of helpers.CASE_FORMS is not in its case's CASE_KERNELS"
        covered = set().union(*(CASE_KERNELS[c] for c in CASES))
        assert used, "no kernel names found in mccnn_cl/"
        missing = sorted(f"{k} ({defined[k]})" for k in used - covered)
        assert not missing, ("kernels used by the package but not run under Oclgrind: "
                             f"{missing}; add them to a case in tests/test_oclgrind.py")

    def test_worker_detects_a_wrong_result():
        """The comparison helper really fails on a wrong element (a test that cannot fail is a defect)."""
        chk = Checks()
        a = np.zeros((2, 3), np.int32)
        b = a.copy()
        b[1, 2] = 1
        chk.close("int", a, b)
        f = np.zeros(4, np.float32)
        g = f.copy()
        g[0] = np.nan
        chk.close("nan", f, g)
        chk.close("tol", f, f + 1e-3, atol=1e-5)
        chk.close("shape", f, f[:3])
        chk.close("poison", np.full(4, POISON), f, atol=1.0)
        assert [r["ok"] for r in chk.results] == [False] * 5


if __name__ == "__main__":
    sys.exit(main())
