"""WTA (left and right), left-right check, interpolation and subpixel kernels
against their numpy twins in mccnn_cl.reference.disparity.

Integer outputs (D^L, D^R, labels, D_INT) are compared exactly.  D_SE is
compared with atol 1e-6: kernel (FP_CONTRACT OFF) and reference evaluate the
same float32 expression in the same order, so they agree to rounding.
"""

import cv2
import numpy as np
import pytest

from mccnn_cl.errors import InputError
from mccnn_cl.reference import disparity as ref
from mccnn_cl.costs.census import CensusCost
from mccnn_cl.stages.disparity import Interpolate, LeftRightCheck, RightReference, Subpixel, WinnerTakeAll

from conftest import POISON

I32_POISON = np.int32(-123456789)


def random_volume(rng, D, H, W, levels=None):
    """Random costs in [0, 1] with NaN in the invalid cells (x - d < 0);
    ``levels`` quantises the costs so that ties are frequent."""
    C = rng.random((D, H, W), dtype=np.float32)
    if levels:
        C = (np.floor(C * levels) / levels).astype(np.float32)
    for d in range(D):
        C[d, :, :min(d, W)] = np.nan
    return C


def poisoned(ctx, nbytes, value=POISON, dtype=np.float32):
    buf = ctx.empty(nbytes, "poisoned output")
    ctx.fill(buf, value, nbytes, dtype)
    return buf


def run_wta(ctx, C):
    D, H, W = C.shape
    wta = WinnerTakeAll(ctx)
    d_cost = ctx.to_device(C)
    dl = wta.left(d_cost, D, H, W, out=poisoned(ctx, H * W * 4, I32_POISON, np.int32))
    dr = wta.right(d_cost, D, H, W, out=poisoned(ctx, H * W * 4, I32_POISON, np.int32))
    return ctx.from_device(dl, (H, W), np.int32), ctx.from_device(dr, (H, W), np.int32)


def run_lr(ctx, DL, DR, D, threshold=1.0):
    H, W = DL.shape
    out = LeftRightCheck(ctx)(ctx.to_device(DL), ctx.to_device(DR), D, H, W, threshold,
                              out=poisoned(ctx, H * W * 4, I32_POISON, np.int32))
    return ctx.from_device(out, (H, W), np.int32)


def run_interp(ctx, DL, labels, directions="paper"):
    H, W = DL.shape
    out = Interpolate(ctx)(ctx.to_device(DL), ctx.to_device(labels), H, W, directions,
                           out=poisoned(ctx, H * W * 4, I32_POISON, np.int32))
    return ctx.from_device(out, (H, W), np.int32)


def run_subpixel(ctx, C, DINT, **kw):
    D, H, W = C.shape
    out = Subpixel(ctx)(ctx.to_device(C), ctx.to_device(DINT), D, H, W,
                        out=poisoned(ctx, H * W * 4), **kw)
    return ctx.from_device(out, (H, W))


@pytest.fixture(scope="module")
def cones(shared_data):
    """A 61 x 97 crop of Middlebury Cones and its census cost (D = 32, cropped 53 x 89)."""
    d = shared_data / "middlebury" / "Cones"
    left = cv2.imread(str(d / "im0.png"), cv2.IMREAD_GRAYSCALE)[150:211, 180:277].astype(np.float32) / 255
    right = cv2.imread(str(d / "im1.png"), cv2.IMREAD_GRAYSCALE)[150:211, 180:277].astype(np.float32) / 255
    assert left.std() > 0.05 and right.std() > 0.05
    C = ref.census_cost(left, right, 32)
    return left, right, C


@pytest.mark.parametrize("D,H,W,levels", [(16, 37, 53, None), (16, 9, 23, 4), (40, 5, 31, 3), (7, 1, 13, 2)])
def test_wta_random(ctx, D, H, W, levels):
    rng = np.random.default_rng(D * 1000 + H)
    C = random_volume(rng, D, H, W, levels)
    DL, DR = run_wta(ctx, C)
    np.testing.assert_array_equal(DL, ref.wta_left(C))
    np.testing.assert_array_equal(DR, ref.wta_right(C))
    x = np.arange(W)
    assert (DL <= x).all() and (DR <= W - 1 - x).all() and DL.min() >= 0 and DR.min() >= 0
    if levels:  # ties present: the smallest d wins
        assert len(np.unique(C[~np.isnan(C)])) <= levels + 1


@pytest.mark.parametrize("chunks", [1, 3, 8])
def test_wta_left_chunks_per_work_item(ctx, chunks):
    """Any number of 16-pixel chunks per work-item of the left WTA (WTA_CHUNKS; the rule
    gives CPUs 8, GPUs 1) gives the reference's map: rows that end inside a work-item's
    last chunk and mid-way through its chunks, D beyond the width of a work-item's first
    chunks, ties."""
    rng = np.random.default_rng(chunks)
    for D, H, W, levels in ((40, 5, 83, None), (9, 3, 200, 3), (70, 2, 53, None)):
        C = random_volume(rng, D, H, W, levels)
        wta = WinnerTakeAll(ctx, chunks=chunks)
        assert wta.chunks == chunks
        out = wta.left(ctx.to_device(C), D, H, W, out=poisoned(ctx, H * W * 4, I32_POISON, np.int32))
        np.testing.assert_array_equal(ctx.from_device(out, (H, W), np.int32), ref.wta_left(C))
    with pytest.raises(InputError):
        WinnerTakeAll(ctx, chunks=0)


@pytest.mark.parametrize("chunks", [1, 3, 8])
def test_wta_invalid_cells_holding_finite_values(ctx, chunks):
    """Validity by index, never by value: a volume whose invalid cells (x < d)
    hold -1000 (below every cost), 0 or +1000 instead of NaN gives both WTAs the
    reference's maps of the NaN-filled volume (a comparison with NaN is false,
    so a kernel that forgets the index rule passes on NaN-filled volumes alone).
    Left WTA with 1, 3 and 8 chunks per work-item; D > W; ties."""
    rng = np.random.default_rng(31 + chunks)
    wta = WinnerTakeAll(ctx, chunks=chunks)
    for D, H, W, levels in ((40, 5, 83, None), (9, 3, 40, 3), (30, 4, 11, None)):
        C = random_volume(rng, D, H, W, levels)
        want_l, want_r = ref.wta_left(C), ref.wta_right(C)
        for value in (-1000.0, 0.0, 1000.0):
            d_c = ctx.to_device(np.where(np.isnan(C), np.float32(value), C))
            dl = wta.left(d_c, D, H, W, out=poisoned(ctx, H * W * 4, I32_POISON, np.int32))
            dr = wta.right(d_c, D, H, W, out=poisoned(ctx, H * W * 4, I32_POISON, np.int32))
            msg = f"{D}x{H}x{W}: invalid cells = {value}"
            np.testing.assert_array_equal(ctx.from_device(dl, (H, W), np.int32), want_l, err_msg=msg)
            np.testing.assert_array_equal(ctx.from_device(dr, (H, W), np.int32), want_r, err_msg=msg)


def test_wta_right_matches_materialised_right_volume(ctx):
    rng = np.random.default_rng(5)
    C = random_volume(rng, 12, 6, 29)
    _, DR = run_wta(ctx, C)
    CR = ref.right_cost_volume(C)
    # argmin over the materialised C_R (NaN = invalid) equals the derived D^R
    expect = np.nanargmin(np.where(np.isnan(CR), np.inf, CR), axis=0)
    np.testing.assert_array_equal(DR, expect)


def test_wta_ties_smallest_d(ctx):
    C = np.zeros((5, 2, 8), np.float32)
    for d in range(5):
        C[d, :, :d] = np.nan
    DL, DR = run_wta(ctx, C)
    assert (DL == 0).all() and (DR == 0).all()


def test_wta_d_larger_than_width(ctx):
    rng = np.random.default_rng(9)
    C = random_volume(rng, 30, 4, 11)  # D >= W: many fully invalid planes
    DL, DR = run_wta(ctx, C)
    np.testing.assert_array_equal(DL, ref.wta_left(C))
    np.testing.assert_array_equal(DR, ref.wta_right(C))


def test_wta_and_lr_real(ctx, cones):
    _, _, C = cones
    D = C.shape[0]
    DL, DR = run_wta(ctx, C)
    np.testing.assert_array_equal(DL, ref.wta_left(C))
    np.testing.assert_array_equal(DR, ref.wta_right(C))
    labels = run_lr(ctx, DL, DR, D)
    np.testing.assert_array_equal(labels, ref.lr_check(DL, DR, D))
    assert {0, 1, 2} <= set(np.unique(labels))  # all three classes present on real data
    dint = run_interp(ctx, DL, labels)
    np.testing.assert_array_equal(dint, ref.interpolate(DL, labels))
    dint_code = run_interp(ctx, DL, labels, "code")
    np.testing.assert_array_equal(dint_code, ref.interpolate(DL, labels, "code", stop_at_any=True))
    for kw in ({"clamp_step": False}, {"clamp_step": True}, {"min_denominator": 1e-5, "clamp_step": True}):
        dse = run_subpixel(ctx, C, dint, **kw)
        np.testing.assert_allclose(dse, ref.subpixel(C, dint, **kw), rtol=0, atol=1e-6)
        assert np.abs(dse - dint).max() > 0.1  # the correction does act


@pytest.mark.parametrize("D,H,W,threshold", [(16, 37, 53, 1.0), (9, 7, 23, 1.1), (25, 3, 20, 0.0), (4, 1, 9, 1.0)])
def test_lr_check_random(ctx, D, H, W, threshold):
    rng = np.random.default_rng(W)
    x = np.arange(W)
    DL = np.floor(rng.random((H, W)) * (np.minimum(D - 1, x) + 1)).astype(np.int32)
    DR = np.floor(rng.random((H, W)) * (np.minimum(D - 1, W - 1 - x) + 1)).astype(np.int32)
    labels = run_lr(ctx, DL, DR, D, threshold)
    np.testing.assert_array_equal(labels, ref.lr_check(DL, DR, D, threshold))


def test_lr_check_threshold_variant_same_on_integers(ctx, cones):
    _, _, C = cones
    DL, DR = ref.wta_left(C), ref.wta_right(C)
    np.testing.assert_array_equal(run_lr(ctx, DL, DR, 32, 1.0), run_lr(ctx, DL, DR, 32, 1.1))


def test_lr_check_hand_made(ctx):
    # one row, W = 6, D = 3
    DL = np.array([[0, 1, 2, 2, 0, 1]], np.int32)
    DR = np.array([[0, 0, 0, 2, 2, 0]], np.int32)
    # x=0: d=0, DR[0]=0 -> correct; x=1: d=1, DR[0]=0 -> |1-0|<=1 correct
    # x=2: d=2, DR[0]=0 -> 2 > 1; others: d'=0 DR[2]=0 ok -> mismatch
    # x=3: d=2, DR[1]=0 -> 2; d'=0: DR[3]=2 -> 2; d'=1: DR[2]=0 -> 1 <= 1 -> mismatch
    # x=4: d=0, DR[4]=2 -> 2; d'=1: DR[3]=2 -> 1 -> mismatch
    # x=5: d=1, DR[4]=2 -> 1 -> correct
    labels = run_lr(ctx, DL, DR, 3)
    np.testing.assert_array_equal(labels, [[0, 0, 1, 1, 1, 0]])
    DR2 = np.array([[5, 5, 5, 5, 5, 5]], np.int32)  # nothing consistent -> occlusion
    np.testing.assert_array_equal(run_lr(ctx, DL, DR2, 3), [[2] * 6])


@pytest.mark.parametrize("H,W,p", [(37, 53, (0.5, 0.3, 0.2)), (1, 29, (0.3, 0.3, 0.4)),
                                   (11, 13, (0.05, 0.55, 0.4)), (8, 9, (0.0, 0.5, 0.5))])
def test_interpolate_random(ctx, H, W, p):
    rng = np.random.default_rng(H * W)
    DL = rng.integers(0, 20, (H, W), dtype=np.int32)
    labels = rng.choice(3, size=(H, W), p=p).astype(np.int32)
    for directions, any_ in (("paper", False), ("code", True)):
        out = run_interp(ctx, DL, labels, directions)
        np.testing.assert_array_equal(out, ref.interpolate(DL, labels, directions, stop_at_any=any_))


def test_interpolate_hand_made(ctx):
    DL = np.array([[7, 3, 9, 4, 8]], np.int32)
    labels = np.array([[2, 0, 2, 2, 0]], np.int32)
    # x=0 occluded, nothing correct on the left -> first correct moving right (3)
    # x=2, x=3 occluded -> first correct moving left (x=1: 3)
    np.testing.assert_array_equal(run_interp(ctx, DL, labels), [[3, 3, 3, 3, 8]])
    # no correct pixel at all: every value kept
    none = np.array([[2, 1, 2, 1, 1]], np.int32)
    np.testing.assert_array_equal(run_interp(ctx, DL, none), DL)
    # a mismatch pixel in a 3x3 block of correct pixels: 8 of the 16 directions
    # hit a neighbour at step 1, the others (2,1)-type steps leave the image
    DL3 = np.arange(9, dtype=np.int32).reshape(3, 3)
    lab3 = np.zeros((3, 3), np.int32)
    lab3[1, 1] = 1
    out = run_interp(ctx, DL3, lab3)
    vals = sorted([0, 1, 2, 3, 5, 6, 7, 8])
    assert out[1, 1] == vals[len(vals) // 2] == 5  # upper median of an even count


@pytest.mark.parametrize("D,H,W", [(16, 37, 53), (30, 3, 11), (3, 1, 17)])
def test_subpixel_random(ctx, D, H, W):
    rng = np.random.default_rng(D + H)
    C = random_volume(rng, D, H, W)
    DINT = rng.integers(0, D, (H, W), dtype=np.int32)  # includes ends and invalid d > x
    for kw in ({"clamp_step": False}, {"min_denominator": 1e-5, "clamp_step": True}):
        out = run_subpixel(ctx, C, DINT, **kw)
        expect = ref.subpixel(C, DINT, **kw)
        np.testing.assert_allclose(out, expect, rtol=0, atol=1e-6)
        assert np.isfinite(out).all()
        if kw["clamp_step"]:
            assert np.abs(out - DINT).max() <= 1.0 + 1e-6
    # the stage's default clamps (test_subpixel_clamps_by_default)
    np.testing.assert_array_equal(run_subpixel(ctx, C, DINT), run_subpixel(ctx, C, DINT, clamp_step=True))


def test_subpixel_guards(ctx):
    D, H, W = 5, 1, 8
    C = np.zeros((D, H, W), np.float32)
    C[:, 0, :] = np.array([0.5, 0.2, 0.4, 0.4, 0.1], np.float32)[:, None]  # minimum at d=1, flat at 2-3
    for d in range(D):
        C[d, :, :d] = np.nan
    DINT = np.array([[0, 1, 1, 2, 1, 4, 3, 1]], np.int32)
    out = run_subpixel(ctx, C, DINT)
    # x=0,1: d+1 > x -> kept; x=2: d=1 -> 1 - (0.4-0.5)/(2*0.5) = 1.1
    # x=3: d=2 -> C-=0.2, C=0.4, C+=0.4: denom -0.2 < 0 -> kept
    # x=5: d = D-1 -> kept; x=6: d=3 -> denom 0.1-0.8+0.4 < 0 -> kept
    np.testing.assert_allclose(out, [[0, 1, 1.1, 2, 1.1, 4, 3, 1.1]], atol=1e-6)


def test_subpixel_clamps_by_default(ctx):
    """Subpixel's default is the matcher's (Hyperparameters.subpixel_clamp, True, the released
    code's): a step over one level (a D_INT that is no cost minimum, as interpolation gives)
    is clamped to [-1, 1] unless clamp_step=False asks for the paper's unbounded formula.
    (Before, the stage's default was False: 20.5 here instead of 2.)"""
    from mccnn_cl.hyperparameters import Hyperparameters

    assert Hyperparameters().subpixel_clamp is True
    D, H, W = 5, 2, 8
    C = np.zeros((D, H, W), np.float32)
    C[:, :, :] = np.array([0.5, 0.3, 0.11, 0.9, 0.9], np.float32)[:, None, None]  # at d = 1: step -19.5
    for d in range(D):
        C[d, :, :d] = np.nan
    DINT = np.ones((H, W), np.int32)  # x = 0, 1: d + 1 > x, kept
    unclamped = run_subpixel(ctx, C, DINT, clamp_step=False)
    np.testing.assert_allclose(unclamped[:, 2:], 20.5, rtol=1e-5)  # the fit is far off: 1 + 19.5
    default = run_subpixel(ctx, C, DINT)
    np.testing.assert_array_equal(default, run_subpixel(ctx, C, DINT, clamp_step=True))
    np.testing.assert_array_equal(default, [[1, 1] + [2] * (W - 2)] * H)
    np.testing.assert_allclose(default, ref.subpixel(C, DINT, clamp_step=True), rtol=0, atol=1e-6)


def test_census_volume_with_stages(ctx, cones):
    """The census kernel's volume feeds the WTA kernels like the reference's."""
    left, right, C = cones
    D, H, W = C.shape
    d_cost = poisoned(ctx, C.nbytes)  # every output poisoned: a cell left unwritten fails
    assert CensusCost(ctx)(left, right, 32, out=d_cost) is d_cost
    got = ctx.from_device(d_cost, C.shape)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(C))
    np.testing.assert_array_equal(got[~np.isnan(C)], C[~np.isnan(C)])
    wta = WinnerTakeAll(ctx)
    dl = wta.left(d_cost, D, H, W, out=poisoned(ctx, H * W * 4, I32_POISON, np.int32))
    DL = ctx.from_device(dl, (H, W), np.int32)
    np.testing.assert_array_equal(DL, ref.wta_left(C))


@pytest.mark.parametrize("lines", [False, True], ids=["block-per-item", "line-per-item"])
@pytest.mark.parametrize("D,H,W", [(16, 37, 53), (20, 3, 11), (1, 1, 9), (31, 2, 32), (40, 3, 97), (33, 2, 65)])
def test_right_reference_volume_and_mirror(ctx, D, H, W, lines):
    """The mirrored right-reference volume, made in place, is C_R mirrored left
    to right (exact copies, NaN exactly at d > x), its left WTA mirrored back
    is D^R, and a second call gives C_L back (its invalid cells as NaN).  The
    invalid cells hold finite values before the call (the kernel must write
    them), and the sizes cover lines with no, some and only whole 16-cell
    blocks, odd and even segment lengths and a middle cell.  Both launch forms
    (a work-item per 16-pair block, or per line: rule ``mirror_lines``)."""
    rng = np.random.default_rng(D * W)
    C = random_volume(rng, D, H, W, levels=5)
    C_dirty = C.copy()
    C_dirty[np.isnan(C_dirty)] = POISON  # invalid cells with a finite value
    rr = RightReference(ctx, lines=lines)
    assert rr.lines is lines
    d_c = ctx.to_device(C_dirty, writable=True)
    assert rr.volume(d_c, D, H, W) is d_c
    CRm = ctx.from_device(d_c, (D, H, W))
    expect = ref.right_cost_volume(C)[:, :, ::-1]
    np.testing.assert_array_equal(np.isnan(CRm), np.isnan(expect))
    np.testing.assert_array_equal(CRm[~np.isnan(CRm)], expect[~np.isnan(expect)])
    for d in range(D):
        assert np.isnan(CRm[d, :, :min(d, W)]).all() and not np.isnan(CRm[d, :, d:]).any()
    dl = WinnerTakeAll(ctx).left(d_c, D, H, W)
    back = rr.mirror(dl, H, W, out=poisoned(ctx, H * W * 4, I32_POISON, np.int32))
    np.testing.assert_array_equal(ctx.from_device(back, (H, W), np.int32), ref.wta_right(C))
    rr.volume(d_c, D, H, W)  # and back: C_L, NaN where invalid
    again = ctx.from_device(d_c, (D, H, W))
    np.testing.assert_array_equal(np.isnan(again), np.isnan(C))
    np.testing.assert_array_equal(again[~np.isnan(C)], C[~np.isnan(C)])
