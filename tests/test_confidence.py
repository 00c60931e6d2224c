"""The confidence stage (kernels/confidence.cl) against its numpy twin
(mccnn_cl.reference.confidence) and against hand-computed curves; through
StereoMatcher.compute(..., confidence=True) and ``mccnn-cl match
--confidence/--labels``; metrics.sparsification.

Tolerance kernel vs reference: 1e-6 absolute.  Both compute the same float32
expression (two subtractions, one addition, one division) on the same
values; the only difference allowed is the division, which OpenCL may round
within 2.5 ulp (no -cl-fp32-correctly-rounded-divide-sqrt), i.e. < 3e-7 on
values <= 1.  Run selection (plateaus, local minima) uses exact float
comparisons on identical values, so a wrong run logic shows as errors of
order 0.1, far above it.
"""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from mccnn_cl.errors import InputError
from mccnn_cl.io import read_pfm
from mccnn_cl.evaluation.metrics import sparsification
from mccnn_cl.pipeline import StereoMatcher
from mccnn_cl.reference import confidence as ref
from mccnn_cl.reference import disparity as dref
from mccnn_cl.costs.census import CensusCost
from mccnn_cl.stages.confidence import Confidence, cost_floor
from mccnn_cl.stages.disparity import LeftRightCheck, WinnerTakeAll

from conftest import POISON

ATOL = 1e-6


def random_volume(rng, D, H, W, levels=None, invalid=np.nan):
    """Random costs in [0, 1) (quantised to ``levels`` values: plateaus and
    ties), ``invalid`` in the cells x - d < 0."""
    C = rng.random((D, H, W), dtype=np.float32)
    if levels:
        C = (np.floor(C * levels) / levels).astype(np.float32)
    for d in range(D):
        C[d, :, :min(d, W)] = invalid
    return C


def run_conf(ctx, C, labels, floor=0.0, half=False, **kw):
    """The stage's map, written into a buffer poisoned first; ``kw``: right_width, first_column."""
    D, H, W = C.shape
    out = ctx.empty(H * W * 4, "poisoned confidence")
    ctx.fill(out, POISON, H * W * 4)
    Confidence(ctx, half=half)(ctx.to_device(np.ascontiguousarray(C)), ctx.to_device(labels.astype(np.int32)),
                               D, H, W, floor, out=out, **kw)
    return ctx.from_device(out, (H, W))


def lr_labels(C):
    D = C.shape[0]
    return dref.lr_check(dref.wta_left(C), dref.wta_right(C), D)


# -- the measure on hand-made curves -------------------------------------
CURVES = [  # (curve, floor, expected)
    ([3, 1, 2, 0.5, 4], 0.0, (1 - 0.5) / (0.5 + 1)),       # two local minima
    ([2, 1, 1, 2, 1], 0.0, 0.0),                            # a plateau and a single cell at the same cost
    ([3, 2, 2, 1, 4], 0.0, (4 - 1) / (1 + 4)),              # a descending shoulder is no minimum: c2 = max
    ([1, 2, 3, 4, 5], 0.0, (5 - 1) / (1 + 5)),              # minimum at the range's start
    ([5, 4, 4, 4, 2], 0.0, (5 - 2) / (2 + 5)),              # at its end, after a plateau
    ([0.25, 0.25, 0.25, 0.25, 0.25], 0.0, 0.0),             # flat
    ([0, 1, 0, 1, 1], 0.0, 0.0),                            # both minima at the floor
    ([-0.9, 0.2, -0.5, 0.3, 0.1], -1.0, (0.4) / (0.1 + 0.5)),  # fst-like, floor -1
    ([0.5, 0.3, 0.6, 0.1, 0.9], -1.0, (0.3 - 0.1) / (1.1 + 1.3)),
]


@pytest.mark.parametrize("curve,floor,want", CURVES)
def test_reference_on_hand_made_curves(curve, floor, want):
    assert ref.curve_confidence(np.array(curve, np.float32), floor) == pytest.approx(want, abs=1e-6)


def test_kernel_on_hand_made_curves(ctx):
    """Each curve in the last column of its own row (x = W-1 >= D-1: every level valid)."""
    for floor in (0.0, -1.0):
        rows = [c for c, f, _ in CURVES if f == floor]
        D, H, W = 5, len(rows), 6
        C = random_volume(np.random.default_rng(0), D, H, W)
        for y, c in enumerate(rows):
            C[:, y, W - 1] = c
        got = run_conf(ctx, C, np.zeros((H, W), np.int32), floor)
        want = [w for _, f, w in CURVES if f == floor]
        np.testing.assert_allclose(got[:, W - 1], want, atol=ATOL)


def test_invariant_under_scaling_about_the_floor(ctx):
    """c -> f + a (c - f): e.g. SGM's path sums on another scale, fst's range.
    Costs k/32 - 1 and power-of-two scales: the scaled volume is exact, so the
    results agree to the division's rounding."""
    rng = np.random.default_rng(5)
    C = random_volume(rng, 16, 9, 23, levels=64) * 2 - 1  # k/32 - 1 in [-1, 1)
    lab = lr_labels(C)
    base = run_conf(ctx, C, lab, -1.0)
    for a in (0.25, 8.0):
        np.testing.assert_allclose(run_conf(ctx, (-1 + a * (C + 1)).astype(np.float32), lab, -1.0), base,
                                   atol=ATOL)
    assert base.std() > 0.05


# -- kernel vs reference ---------------------------------------------------
@pytest.mark.parametrize("D,H,W,levels", [(16, 37, 53, None), (16, 9, 23, 4), (40, 5, 31, 3), (7, 1, 13, 2),
                                          (1, 3, 7, None), (5, 4, 1, None)])
def test_kernel_matches_reference_on_random_volumes(ctx, D, H, W, levels):
    rng = np.random.default_rng(D * 1000 + H * 10 + W)
    C = random_volume(rng, D, H, W, levels)
    assert np.nanstd(C) > 0 or D == 1
    for lab in (lr_labels(C), np.zeros((H, W), np.int32)):  # the real labels; every pixel correct
        got = run_conf(ctx, C, lab)
        want = ref.confidence(C, lab)
        np.testing.assert_allclose(got, want, atol=ATOL)
        assert np.all(got[lab != dref.CORRECT] == 0)
        assert np.all((got >= 0) & (got <= 1))
    if D > 1 and W > 1:
        assert want.max() > 0.1  # the all-correct run measured something


@pytest.mark.parametrize("floor", [0.0, -1.0])
def test_invalid_cells_are_never_read(ctx, floor):
    """Validity by index: invalid cells holding a value below every cost (the
    minima), the floor, one inside the cost range, or one above every cost (the
    largest cost, taken when a curve has one local minimum) instead of NaN
    change nothing, bit for bit.  Plateaus (levels) and D > W columns included."""
    rng = np.random.default_rng(11)
    for D, H, W, levels in ((20, 7, 29, None), (16, 5, 23, 4), (24, 3, 17, None)):
        C = random_volume(rng, D, H, W, levels)
        lab = np.zeros((H, W), np.int32)
        base = run_conf(ctx, C, lab, floor)
        np.testing.assert_allclose(base, ref.confidence(C, lab, floor), atol=ATOL)
        for value in (-1000.0, floor, 0.5, 1000.0):
            dirty = np.where(np.isnan(C), np.float32(value), C)
            np.testing.assert_array_equal(run_conf(ctx, dirty, lab, floor).view(np.uint32), base.view(np.uint32),
                                          err_msg=f"{D}x{H}x{W}: invalid cells = {value}")


def test_half_storage(ctx):
    rng = np.random.default_rng(3)
    C = random_volume(rng, 16, 37, 53).astype(np.float16)
    lab = lr_labels(C.astype(np.float32))
    got = run_conf(ctx, C, lab, half=True)
    np.testing.assert_allclose(got, ref.confidence(C, lab), atol=ATOL)
    # and the half rounding itself moves the confidence little
    full = ref.confidence(C.astype(np.float32), lab)
    assert np.mean(np.abs(got - full) < 1e-2) > 0.99


# -- ranges with M < 0: the working frame's padding ---------------------------
def _image_rule_confidence(C, labels, floor=0.0):
    """The measure in the image's frame: each pixel's curve is its finite cells (the
    real range's cells with a real right pixel; the rest NaN, as StereoResult's C and
    RangeFrame.valid say), 0 where the label is not CORRECT."""
    D, H, W = C.shape
    out = np.zeros((H, W), np.float32)
    for y in range(H):
        for x in range(W):
            c = C[:, y, x]
            if labels[y, x] == dref.CORRECT:
                out[y, x] = ref.curve_confidence(c[np.isfinite(c)], floor)
    return out


@pytest.mark.parametrize("half", [False, True], ids=["float32", "float16"])
@pytest.mark.parametrize("M,D,W", [(-6, 16, 29), (-20, 24, 37), (-3, 40, 21), (-9, 5, 19)])
def test_negative_range_padding_is_never_read(ctx, half, M, D, W):
    """The working frame of a range M .. M+D-1 with M < 0 (mccnn_cl/disprange.py): the
    volume has p = -M padding columns on the left (x' < p) and cells whose right pixel is
    the padding (x' - d' >= W, W the real width).  With right_width=W and first_column=p
    the kernel equals the reference, the measure taken in the image's frame over the real
    cells only, and any value in the padding's cells (NaN, huge, below every cost, the
    floor) changes nothing, bit for bit; the padding's columns get 0.  Without them (the
    defaults, the real pair's: the stage's only behaviour before) the padding is part of
    the curves: the map changes with the padding's values.  D > p and D < p (M = -9, D = 5:
    the last real columns have no level with a real right pixel, and get 0)."""
    from mccnn_cl.disprange import RangeFrame

    p, Ww, H = -M, W - M, 5
    rng = np.random.default_rng(W * 100 + D)
    base_vol = random_volume(rng, D, H, Ww, levels=8)
    d = np.arange(D)[:, None]
    x = np.arange(Ww)[None, :]
    pad = np.broadcast_to(((x < p) | (x - d >= W)) & (x - d >= 0), (H, D, Ww)).transpose(1, 0, 2)
    assert pad.any() and (~pad & ~np.isnan(base_vol)).any()
    dtype = np.float16 if half else np.float32
    huge = 6.0e4 if half else 1.0e30
    labels = [np.zeros((H, Ww), np.int32), rng.choice(3, size=(H, Ww), p=(0.6, 0.2, 0.2)).astype(np.int32)]
    frame = RangeFrame(M, D, (H, W), 0)
    assert frame.masked and frame.p == p and frame.Ww == Ww and frame.W == W
    for floor in (0.0, -1.0):
        for lab in labels:
            C = np.where(pad, np.float32(np.nan), base_vol).astype(dtype)
            base = run_conf(ctx, C, lab, floor, half, right_width=W, first_column=p)
            want = ref.confidence(C, lab, floor, right_width=W, first_column=p)
            np.testing.assert_allclose(base, want, atol=ATOL)
            assert np.all(np.isfinite(base)) and np.all((base >= 0) & (base <= 1))
            assert np.all(base[:, :p] == 0) and np.all(base[lab != dref.CORRECT] == 0)
            # the image's frame: C moved back (x = x' - p), the invalid and padding cells NaN
            real = frame.left(C.astype(np.float32), np.nan)
            real[~np.broadcast_to(frame.valid(), real.shape)] = np.nan
            np.testing.assert_allclose(base[:, p:], _image_rule_confidence(real, lab[:, p:], floor), atol=ATOL)
            if lab is labels[0]:
                assert base[:, p:].max() > 0.1  # the all-correct run measured something
            changed = False
            for value in (np.nan, -huge, -1000.0, floor, 0.5, 1000.0, huge):
                dirty = np.where(pad, np.float32(value), base_vol).astype(dtype)
                got = run_conf(ctx, dirty, lab, floor, half, right_width=W, first_column=p)
                np.testing.assert_array_equal(got.view(np.uint32), base.view(np.uint32),
                                              err_msg=f"padding = {value}, floor {floor}")
                old = run_conf(ctx, dirty, lab, floor, half)  # padding read (defaults: the real pair)
                changed |= bool((old[:, p:] != base[:, p:]).any())
            assert changed


def test_confidence_arguments_checked(ctx):
    d = ctx.to_device(np.zeros((3, 2, 5), np.float32))
    lab = ctx.to_device(np.zeros((2, 5), np.int32))
    with pytest.raises(InputError, match="right_width"):
        Confidence(ctx)(d, lab, 3, 2, 5, right_width=6)
    with pytest.raises(InputError, match="right_width"):
        Confidence(ctx)(d, lab, 3, 2, 5, right_width=0)
    with pytest.raises(InputError, match="first_column"):
        Confidence(ctx)(d, lab, 3, 2, 5, first_column=5)


@pytest.fixture(scope="module")
def kitti_crop(shared_data):
    d = shared_data / "kitti2015" / "training"
    left = cv2.imread(str(d / "image_2" / "000000_10.png"), cv2.IMREAD_GRAYSCALE)[180:241, 400:531]
    right = cv2.imread(str(d / "image_3" / "000000_10.png"), cv2.IMREAD_GRAYSCALE)[180:241, 400:531]
    assert left.std() > 10 and right.std() > 10
    return left, right


def test_real_census_volume(ctx, kitti_crop):
    """The census cost of a KITTI crop (costs k/bits: plateaus everywhere), its
    labels from the device WTA and left-right check."""
    left, right = (a.astype(np.float32) / 255 for a in kitti_crop)
    D = 48
    cost = CensusCost(ctx)
    d_C = cost(left, right, D)
    H, W = left.shape[0] - 2 * cost.margin, left.shape[1] - 2 * cost.margin
    wta = WinnerTakeAll(ctx)
    d_lab = LeftRightCheck(ctx)(wta.left(d_C, D, H, W), wta.right(d_C, D, H, W), D, H, W)
    C = ctx.from_device(d_C, (D, H, W))
    lab = ctx.from_device(d_lab, (H, W), np.int32)
    assert 0.2 < np.mean(lab == 0) < 0.95
    got = run_conf(ctx, C, lab)
    want = ref.confidence(C, lab)
    np.testing.assert_allclose(got, want, atol=ATOL)
    assert want[lab == 0].std() > 0.02


def test_cost_floor_table():
    assert cost_floor("census") == 0.0 and cost_floor("mccnn-fst") == -1.0
    with pytest.raises(InputError, match="no cost floor"):
        cost_floor("sad")


# -- pipeline ---------------------------------------------------------------
def test_pipeline_confidence(ctx, kitti_crop):
    left, right = kitti_crop
    m = StereoMatcher(cost="census", max_disparity=48, device=ctx)
    full = m.compute(left, right, return_intermediates=True, confidence=True)
    mg = full.margin
    # the final volume C and the labels the pipeline used, through the reference
    want = ref.confidence(full.intermediates["C"], full.intermediates["labels"])
    np.testing.assert_allclose(full.intermediates["confidence"], want, atol=ATOL)
    # image-sized, border as Enlarge (the reference enlarge of the cropped map)
    assert full.confidence.shape == left.shape and full.confidence.dtype == np.float32
    np.testing.assert_array_equal(full.confidence, dref.enlarge(want, mg, left.shape))
    np.testing.assert_array_equal(full.labels[mg:-mg, mg:-mg], full.intermediates["labels"])
    np.testing.assert_array_equal(full.labels, np.pad(full.intermediates["labels"], mg, mode="edge"))
    # the flag alone: same maps, nothing else copied
    only = m.compute(left, right, confidence=True)
    np.testing.assert_array_equal(only.confidence, full.confidence)
    np.testing.assert_array_equal(only.labels, full.labels)
    np.testing.assert_array_equal(only.disparity, full.disparity)
    assert only.intermediates == {}
    plain = m.compute(left, right, return_intermediates=True)
    assert plain.confidence is None and plain.labels is None and "confidence" not in plain.intermediates
    assert np.all(only.confidence[only.labels != 0] == 0) and only.confidence.max() > 0.3


def test_pipeline_passes_the_fst_floor(ctx, kitti_crop):
    """An fst network (costs -cosine in [-1, 1]): the pipeline measures from f = -1."""
    from mccnn_cl.weights import Weights

    left, right = kitti_crop
    m = StereoMatcher(weights=Weights.random([[8, 3], [8, 3]], architecture="mccnn-fst", seed=2),
                      max_disparity=24, device=ctx)
    assert m.cost_floor == -1.0
    res = m.compute(left, right, return_intermediates=True, confidence=True)
    C, lab = res.intermediates["C"], res.intermediates["labels"]
    assert np.nanmin(C) < 0  # costs below 0: floor 0 would be wrong here
    np.testing.assert_allclose(res.intermediates["confidence"], ref.confidence(C, lab, -1.0), atol=ATOL)


def test_pipeline_confidence_half_and_tiled(ctx, kitti_crop):
    left, right = kitti_crop
    D = 48
    base = StereoMatcher(cost="census", max_disparity=D, device=ctx).compute(left, right, confidence=True)
    half = StereoMatcher(cost="census", max_disparity=D, device=ctx, volume_dtype="float16")
    res = half.compute(left, right, return_intermediates=True, confidence=True)
    np.testing.assert_allclose(res.intermediates["confidence"],
                               ref.confidence(res.intermediates["C"], res.intermediates["labels"]), atol=ATOL)
    same = res.labels == base.labels
    assert same.mean() > 0.97
    assert np.mean(np.abs(res.confidence - base.confidence)[same] < 0.02) > 0.97
    # row tiles: each tile's core rows assembled; the tiles' cut SGM paths
    # move the costs a little everywhere, so the maps agree closely, not
    # exactly, with the whole-image run (measured: labels 99.7 %, |diff| <
    # 0.05 at 96 %; the same maps one row out of place: 97.2 % and 82 %)
    tiled = StereoMatcher(cost="census", max_disparity=D, device=ctx, memory_limit=4_000_000, tile_overlap=8)
    assert tiled.memory_plan(left.shape).tiled and len(tiled.memory_plan(left.shape).tiles) >= 2
    t = tiled.compute(left, right, confidence=True)
    assert t.confidence.shape == left.shape and np.all(t.confidence[t.labels != 0] == 0)
    assert np.mean(t.labels == base.labels) > 0.99
    assert np.mean(np.abs(t.confidence - base.confidence) < 0.05) > 0.93


def test_pipeline_negative_range_confidence(ctx, kitti_crop):
    """A range with M < 0 (the KITTI crop swapped: disparities negative): the confidence
    the pipeline returns is the measure in the image's frame, over each pixel's real cells
    (StereoResult's C: the padding's cells NaN).  Measured before: 103 of 5822 correct
    pixels differed, by up to 0.5 (their curves took the padding's aggregated costs)."""
    left, right = kitti_crop
    M, D = -40, 48
    m = StereoMatcher(cost="census", max_disparity=D, min_disparity=M, device=ctx)
    res = m.compute(right, left, return_intermediates=True, confidence=True)
    it = res.intermediates
    assert np.mean(it["labels"] == dref.CORRECT) > 0.5
    np.testing.assert_allclose(it["confidence"], _image_rule_confidence(it["C"], it["labels"]), atol=ATOL)
    assert np.all(np.isfinite(res.confidence)) and np.all((res.confidence >= 0) & (res.confidence <= 1))


# -- CLI --------------------------------------------------------------------
@pytest.mark.slow
def test_cli_confidence_and_labels(ctx, kitti_crop, tmp_path):
    left, right = kitti_crop
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    run = [sys.executable, "-m", "mccnn_cl", "match", str(tmp_path / "l.png"), str(tmp_path / "r.png"),
           "--cost", "census", "--max-disp", "48"]
    p = subprocess.run(run + ["-o", str(tmp_path / "o.pfm"), "--confidence", "--labels", str(tmp_path / "lab.npy")],
                       capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stderr
    p = subprocess.run(run + ["-o", str(tmp_path / "o2.pfm"), "--confidence", str(tmp_path / "c.png"),
                              "--labels"], capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stderr
    want = StereoMatcher(cost="census", max_disparity=48, device=ctx).compute(left, right, confidence=True)
    np.testing.assert_allclose(read_pfm(tmp_path / "o_confidence.pfm"), want.confidence, atol=ATOL)
    np.testing.assert_array_equal(np.load(tmp_path / "lab.npy"), want.labels)
    png = cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16
    np.testing.assert_allclose(png / 65535.0, want.confidence, atol=0.5 / 65535 + ATOL)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "o2_labels.png"), cv2.IMREAD_UNCHANGED), want.labels)
    p = subprocess.run(run + ["-o", str(tmp_path / "o3.pfm"), "--confidence", str(tmp_path / "c.jpg")],
                       capture_output=True, text=True, timeout=180)
    assert p.returncode != 0 and "--confidence must end in" in p.stderr and len(p.stderr.strip().splitlines()) == 1


# -- sparsification -----------------------------------------------------------
def test_sparsification_curves():
    rng = np.random.default_rng(2)
    gt = (rng.random((40, 50)) * 20).astype(np.float32)
    pred = gt + rng.normal(0, 3, gt.shape).astype(np.float32)
    pred[0, :5] = np.nan  # no prediction: bad, dropped first by the oracle
    gt[1, :7] = np.nan    # unknown: not evaluated
    err = np.abs(pred - gt)
    rate = 100 * np.mean(~(err[np.isfinite(gt)] <= 3))
    perfect = sparsification(pred, gt, -np.nan_to_num(err, nan=1e9), 3.0)
    assert perfect["curve"][0] == pytest.approx(rate)
    np.testing.assert_allclose(perfect["curve"], perfect["oracle"])
    n = int(np.isfinite(gt).sum())
    kept = 1 - np.round(np.asarray(perfect["fractions"]) * n) / n  # whole pixels are dropped
    np.testing.assert_allclose(perfect["oracle"], 100 * np.maximum(0, rate / 100 - (1 - kept)) / kept, atol=1e-9)
    flat = sparsification(pred, gt, np.zeros_like(gt), 3.0)  # ties dropped pro rata: the rate stays
    np.testing.assert_allclose(flat["curve"], rate)
    assert flat["auc"] == pytest.approx(rate) and flat["oracle_auc"] < rate / 2
    worst = sparsification(pred, gt, np.nan_to_num(err, nan=1e9), 3.0)  # drops the good pixels first
    assert worst["curve"][-1] > rate and worst["auc"] > rate
    with pytest.raises(InputError):
        sparsification(pred, gt, np.zeros((3, 3)), 3.0)
    with pytest.raises(InputError):
        sparsification(pred, gt, np.full_like(gt, np.nan), 3.0)
