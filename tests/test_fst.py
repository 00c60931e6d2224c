"""MC-CNN-fst on the device (features.ConvStack without the last ReLU,
kernels/fst.cl: normalisation and cosine volume) against
mccnn_cl.reference.network.fst_cost_volume.

Tolerance: features are unit vectors, so every cost is a cosine in [-1, 1].
The kernels accumulate in float32 over up to 9 * 64 products per conv unit
and 64 products per cost (another order than the float64 reference); with
He-scale weights the costs differ by ~1e-6.  2e-5 absolute is a bound with
margin that any wrong index, shift, sign, missing ReLU or missing
normalisation exceeds by orders of magnitude (checked below where cheap:
the sign and the ReLU after the last layer).  NaN exactly where x - d < 0.
"""

import cv2
import numpy as np
import pytest

from mccnn_cl.errors import InputError, WeightsError
from mccnn_cl.reference import network as ref
from mccnn_cl.costs import fst as fst_stage
from mccnn_cl.costs.registry import make_cost
from mccnn_cl.costs.fst import FstCost
from mccnn_cl.weights import Weights

from conftest import POISON
from helpers import random_pair, run_poisoned

TOL = 2e-5


def check(got, expected, tol=TOL):
    D, h, w = expected.shape
    assert got.shape == expected.shape
    assert not np.any(got == POISON), "cells left unwritten"
    d, _, x = np.meshgrid(np.arange(D), np.arange(h), np.arange(w), indexing="ij")
    np.testing.assert_array_equal(np.isnan(got), x < d)
    np.testing.assert_array_equal(np.isnan(expected), x < d)
    v = ~np.isnan(expected)
    if v.any():
        err = np.abs(got[v].astype(np.float64) - expected[v]).max()
        assert err <= tol, f"max abs error {err:.3g}"
        assert np.all(np.abs(got[v]) <= 1 + 1e-6)


@pytest.mark.parametrize("case", [
    # conv layers, H x W image, D
    ([[16, 3]] * 4, 37 + 8, 53 + 8, 16),     # the brief's odd size: 37 x 53 volume, D = 16
    ([[64, 3]] * 4, 20, 70, 40),             # KITTI's layers, several 16-pixel blocks
    ([[64, 3]] * 5, 19, 31, 33),             # Middlebury's 5 layers (patch 11), D > W
    ([[7, 3], [5, 5]], 9, 23, 5),            # odd maps, kernel 5, one row
    ([[12, 3]], 5, 8, 1),                    # one layer, D = 1, w < 16
], ids=["37x53-D16", "kitti-layers", "mb-5-layers-D>W", "odd-maps", "one-layer"])
def test_random_images(ctx, case):
    conv, H, W, D = case
    w = Weights.random(conv, architecture="mccnn-fst", seed=H * W)
    left, right = random_pair(np.random.default_rng(H + W), H, W)
    cost = FstCost(ctx, w)
    got = run_poisoned(ctx, cost, left, right, D)
    check(got, ref.fst_cost_volume(w, left, right, D))


@pytest.mark.parametrize("crop", [
    ("kitti2015/training/image_2/000000_10.png", "kitti2015/training/image_3/000000_10.png", 180, 600),
    ("middlebury/Cones/im0.png", "middlebury/Cones/im1.png", 150, 200),
], ids=["kitti2015-000000", "middlebury-cones"])
def test_real_crops(ctx, shared_data, crop):
    lp, rp, y0, x0 = crop
    left = cv2.imread(str(shared_data / lp), cv2.IMREAD_GRAYSCALE)[y0:y0 + 41, x0:x0 + 67]
    right = cv2.imread(str(shared_data / rp), cv2.IMREAD_GRAYSCALE)[y0:y0 + 41, x0:x0 + 67]
    assert left.std() > 5 and right.std() > 5
    w = Weights.random(architecture="mccnn-fst", seed=5)  # 4 x 64 maps, 3 x 3
    expected = ref.fst_cost_volume(w, left, right, 24)
    for vw in (16, 8):  # both widths of the pairs form
        check(run_poisoned(ctx, FstCost(ctx, w, workgroup=False, volume_width=vw), left, right, 24), expected)
    # the best disparity of a real pair is mostly a clear minimum: the costs are not flat
    assert np.nanstd(expected) > 0.05


def test_features_normalised_and_no_last_relu(ctx):
    """fst_normalise's output is the reference's unit vectors, with negative
    components (no ReLU after the last layer); the cost is minus the dot product."""
    w = Weights.random([[8, 3], [8, 3]], architecture="mccnn-fst", seed=2)
    assert not w.relu_after_last_conv
    img = np.random.default_rng(3).random((14, 41)).astype(np.float32)
    cost = FstCost(ctx, w)
    f = cost.features(img)
    fr = ref.fst_features(w, img)
    np.testing.assert_allclose(f, fr, atol=2e-6, rtol=0)
    assert (f < 0).any()
    np.testing.assert_allclose(np.linalg.norm(f, axis=2), 1.0, atol=1e-4)
    # a pair of identical images: the cost at d = 0 is -|f|^2 ~ -1
    got = run_poisoned(ctx, cost, img, img, 3)
    np.testing.assert_allclose(got[0], -1.0, atol=1e-4)


@pytest.mark.parametrize("nk,cs", [(64, 64), (20, 32), (8, 16), (24, 24)])
def test_normalise_forms_same_bits(ctx, nk, cs):
    """fst_normalise16 (16 pixels per work-item, transposed blocks of maps) writes the
    same bits as fst_normalise (one pixel per work-item) into poisoned planes, for map
    counts that are and are not multiples of 16, a channel stride that leaves no room
    past the last map (24), rows whose width is not a multiple of 16, the zero padding
    left and right of each row included; and both equal x / sqrt(|x|^2 + 1e-5) in float64
    to float32 rounding."""
    from mccnn_cl.opencl.context import launch_sizes

    rng = np.random.default_rng(nk)
    h, w = 3, 37
    wp = fst_stage.PADL + -(-w // 32) * 32
    feat = rng.standard_normal((h * w, cs), dtype=np.float32)
    feat[5, :nk] = 0.0  # a pixel whose maps are all 0: 0 / sqrt(1e-5)
    feat[:, nk:] = np.nan  # maps past NK (padding of the stride) must never be read into a result
    d_feat = ctx.to_device(feat)
    got = {}
    for name, px in (("fst_normalise", 1), ("fst_normalise16", 16)):
        kern = ctx.kernel("fst.cl", name, NK=nk, CS=cs, PADL=fst_stage.PADL)
        d_out = ctx.empty(h * nk * wp * 4, "planes")
        ctx.fill(d_out, POISON, h * nk * wp * 4)
        kern(ctx.queue, *launch_sizes(ctx, (wp // px, h), guarded=(1, 0)), d_feat, d_out, np.int32(w),
             np.int32(wp))
        got[name] = ctx.from_device(d_out, (h, nk, wp))
    a, b = got["fst_normalise"], got["fst_normalise16"]
    assert not np.any(b == POISON)
    np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))
    pad = np.ones(wp, bool)
    pad[fst_stage.PADL:fst_stage.PADL + w] = False
    assert np.all(b[:, :, pad] == 0)
    f = feat[:, :nk].astype(np.float64).reshape(h, w, nk)
    want = (f / np.sqrt((f * f).sum(-1, keepdims=True) + 1e-5)).transpose(0, 2, 1)
    np.testing.assert_allclose(b[:, :, fst_stage.PADL:fst_stage.PADL + w], want, rtol=0, atol=1e-6)


def test_cpu_shaped_cost_uses_the_16_pixel_normalise(ctx):
    """The pairs form (CPU-shaped) launches fst_normalise16, the work-group form the
    one-pixel kernel."""
    w = Weights.random([[8, 3]], architecture="mccnn-fst", seed=1)
    assert FstCost(ctx, w, workgroup=False)._norm.function_name == "fst_normalise16"
    assert FstCost(ctx, w, workgroup=True)._norm.function_name == "fst_normalise"


@pytest.mark.parametrize("rows", [1, 3])
def test_bands_and_to_host(ctx, monkeypatch, rows):
    """Bands of 1 and 3 volume rows (seams), to_host in bands: the same values as one band."""
    w = Weights.random([[10, 3]] * 3, architecture="mccnn-fst", seed=4)
    left, right = random_pair(np.random.default_rng(9), 20, 45)
    cost = FstCost(ctx, w)
    whole = run_poisoned(ctx, cost, left, right, 11)
    monkeypatch.setattr(fst_stage, "BAND_BYTES", rows * cost._row_bytes(39))
    assert cost.band_rows(14, 39) == rows
    seen = []
    np.testing.assert_array_equal(run_poisoned(ctx, cost, left, right, 11), whole)
    host = cost.to_host(left, right, 11, max_bytes=11 * 39 * 4 * 2, progress=lambda d, t: seen.append((d, t)))
    np.testing.assert_array_equal(host, whole)
    assert seen[-1] == (11, 11) and all(t == 11 for _, t in seen)


def test_planar_features_kept_between_bands_and_calls(ctx, monkeypatch):
    """The normalised features' buffers come from a pool: a later band or call
    reuses them (no new buffer; a fresh one's first write is page mapping on
    CPU devices) and what they held before changes nothing; to_host and
    release_buffers free them."""
    w = Weights.random([[10, 3]] * 3, architecture="mccnn-fst", seed=5)
    rng = np.random.default_rng(3)
    a, b = random_pair(rng, 20, 45), random_pair(rng, 20, 45)
    cost = FstCost(ctx, w)
    monkeypatch.setattr(fst_stage, "BAND_BYTES", 2 * cost._row_bytes(39))  # bands of 2 of the 14 rows
    run_poisoned(ctx, cost, *a, 11)
    kept = list(cost._planes._free)
    assert len(kept) == 2
    for buf in kept:  # whatever a kept buffer holds must not matter: every cell read is rewritten
        ctx.fill(buf, np.float32(np.nan), buf.size)
    made = []
    real_empty = ctx.empty
    monkeypatch.setattr(ctx, "empty", lambda n, what="buffer": made.append(what) or real_empty(n, what))
    got = run_poisoned(ctx, cost, *b, 11)
    assert "fst planar features" not in made
    assert all(any(k is f for f in cost._planes._free) for k in kept)
    np.testing.assert_array_equal(got, run_poisoned(ctx, FstCost(ctx, w), *b, 11))
    check(got, ref.fst_cost_volume(w, *b, 11))
    cost.to_host(*a, 11)
    assert cost._planes._free == []
    run_poisoned(ctx, cost, *a, 11)
    cost.release_buffers()
    assert cost._planes._free == []


def test_half_storage(ctx):
    w = Weights.random([[16, 3]] * 4, architecture="mccnn-fst", seed=6)
    left, right = random_pair(np.random.default_rng(1), 23, 50)
    got = run_poisoned(ctx, FstCost(ctx, w, half=True), left, right, 9, half=True).astype(np.float32)
    # float16 rounding of values in [-1, 1]: half an ulp at 1 is 2^-11 ~ 4.9e-4
    check(got, ref.fst_cost_volume(w, left, right, 9), tol=5e-4 + TOL)


def test_interface_and_errors(ctx):
    w = Weights.random([[8, 3]] * 2, architecture="mccnn-fst", seed=1)
    cost = make_cost(ctx, w)
    assert isinstance(cost, FstCost) and cost.margin == 2 and not cost.local
    f = cost.flops(30, 40, 10)
    assert f["volume"] == 2 * 8 * f["valid_cells"] and f["valid_cells"] == 26 * sum(36 - d for d in range(10))
    assert cost.scratch_bytes(26, 36) > 0
    with pytest.raises(WeightsError):
        FstCost(ctx, Weights.random([[8, 3]], [4, 2], seed=1))  # a paper network
    img = np.zeros((10, 12), np.float32)
    with pytest.raises(InputError):
        cost(img, img[:, :11], 4)
    with pytest.raises(InputError):
        cost(img, img, 0)
    with pytest.raises(InputError):
        cost(img[:4], img[:4], 3)  # smaller than the 5 x 5 patch


@pytest.mark.parametrize("size", [(37 + 8, 53 + 8, 16), (12, 80, 70), (10, 40, 45), (9, 20, 13)],
                         ids=["37x53-D16", "D70-w72", "D>W", "w12-D13"])
def test_volume_forms(ctx, size):
    """The CPU forms of the volume kernel (fst_volume_pairs on 16-wide vectors,
    FST_VW 8 on 8-wide ones) against the reference and each other bit
    for bit (the same fma chain per cost); widths that end inside an 8-, a 16-
    and a 32-pixel block, D not a multiple of 4, 8 or 16; float16 storage too."""
    H, W, D = size
    w = Weights.random([[16, 3]] * 4, architecture="mccnn-fst", seed=W)
    left, right = random_pair(np.random.default_rng(H), H, W)
    expected = ref.fst_cost_volume(w, left, right, D)
    got = {}
    for vw in (16, 8):
        cost = FstCost(ctx, w, workgroup=False, volume_width=vw)
        assert cost.volume_path == "pairs" and cost.volume_width == vw
        got[vw] = run_poisoned(ctx, cost, left, right, D)
        check(got[vw], expected)
    np.testing.assert_array_equal(got[8], got[16])
    # float16 storage: the same float costs, each rounded to the nearest half on
    # store, so every valid cell is bit for bit the float kernel's value rounded
    # to half (numpy's float16 rounds to nearest even too), NaN exactly in the
    # invalid cells, no poison (-1e4) left; and so within TOL + 2^-11 relative of
    # the reference
    valid = ~np.isnan(expected)
    for vw in (16, 8):
        half = run_poisoned(ctx, FstCost(ctx, w, half=True, workgroup=False, volume_width=vw), left, right, D,
                            half=True)
        assert half.dtype == np.float16 and half.shape == expected.shape
        assert not np.any(half == np.float16(-1e4)), f"width {vw}: cells left unwritten"
        np.testing.assert_array_equal(np.isnan(half), ~valid, err_msg=f"width {vw}")
        np.testing.assert_array_equal(half[valid].view(np.uint16), got[16][valid].astype(np.float16).view(np.uint16),
                                      err_msg=f"width {vw}")
        err = np.abs(half[valid].astype(np.float64) - expected[valid])
        assert np.all(err <= TOL + 2.0 ** -11 * np.abs(expected[valid])), f"width {vw}: max error {err.max():.3g}"


def test_volume_width_rule(ctx, monkeypatch):
    """The pairs form's width follows the rule (0: the device's float vector width, 16 or
    more -> 16, else 8; PoCL on a Zen 3 reports 8), a tuned width wins, a bad one is refused."""
    from dataclasses import replace
    from mccnn_cl.opencl.device import RULES

    assert RULES["fst_volume_width"]["cpu"] == 0
    prof = ctx.profile
    for width, expected in ((16, 16), (8, 8), (4, 8)):
        p = replace(prof, vector_width=width, tuned={})
        assert p.fst_volume_width() == expected
    assert replace(prof, vector_width=16, tuned={"fst_volume_width": 8}).fst_volume_width() == 8
    monkeypatch.setattr(ctx, "profile", replace(prof, vector_width=8, tuned={}))
    w = Weights.random([[8, 3]], architecture="mccnn-fst", seed=1)
    assert FstCost(ctx, w, workgroup=False).volume_width == 8
    with pytest.raises(InputError, match="volume_width"):
        FstCost(ctx, w, workgroup=False, volume_width=4)


def test_fst_matcher_tiles_exact(ctx, shared_data, monkeypatch):
    """The fst cost with the authors' settings (standardised thresholds, no
    CBCA) through StereoMatcher's row tiles whose context spans the image:
    bit for bit the whole-image run (the volume in host memory via to_host,
    in bands of 5 rows)."""
    from mccnn_cl.pipeline import StereoMatcher
    from mccnn_cl.settings import authors_settings

    lp, rp = "kitti2015/training/image_2/000000_10.png", "kitti2015/training/image_3/000000_10.png"
    left = cv2.imread(str(shared_data / lp), cv2.IMREAD_GRAYSCALE)[150:214, 500:700]
    right = cv2.imread(str(shared_data / rp), cv2.IMREAD_GRAYSCALE)[150:214, 500:700]
    w = Weights.random([[16, 3]] * 4, architecture="mccnn-fst", seed=8)
    w.meta["stereo"] = authors_settings("mccnn-fst", "kitti")
    m = StereoMatcher(w, max_disparity=24, device=ctx)
    whole = m.compute(left, right, return_intermediates=True)
    assert not whole.plan.tiled and "cross" not in whole.timings
    H = left.shape[0] - 2 * m.margin
    real_plan = m.memory_plan

    def full_context(shape):
        plan = real_plan(shape)
        plan.tiles = [(0, 20, 0, H), (20, H, 0, H)]
        plan.tiled, plan.tile_budget = True, 5 * 24 * (200 - 8) * 4
        return plan

    monkeypatch.setattr(m, "memory_plan", full_context)
    tiled = m.compute(left, right, return_intermediates=True)
    assert tiled.plan.tiled
    np.testing.assert_array_equal(tiled.disparity, whole.disparity)
    np.testing.assert_array_equal(tiled.intermediates["D_SE"], whole.intermediates["D_SE"])


def test_conv_rn_sets_the_fst_stack_only(ctx):
    """The tiles' CONV_RN (channels per conv work-item) reaches the fst stack, and every
    width gives the same volume bit for bit on the direct GEMM (each output sums its
    terms in one order whatever the tile) and the reference's within TOL; an explicit RN alone still sets
    the stack (as before CONV_RN); the paper network's stack keeps the head's RN."""
    from mccnn_cl.costs.network import PaperCost

    w = Weights.random([[24, 3]] * 3, architecture="mccnn-fst", seed=5)
    left, right = random_pair(np.random.default_rng(5), 14, 45)
    expected = ref.fst_cost_volume(w, left, right, 9)
    vols = []
    for rn in (16, 8, 4):
        cost = FstCost(ctx, w, tiles={"CONV_RN": rn, "CONV_RM": 3}, winograd=False)
        assert cost.stack.rn == rn
        vols.append(run_poisoned(ctx, cost, left, right, 9))
        check(vols[-1], expected)
    for v in vols[1:]:
        np.testing.assert_array_equal(v, vols[0])
    assert FstCost(ctx, w, tiles={"RN": 2}).stack.rn == 2
    assert FstCost(ctx, w).stack.rn == ctx.profile.network_tiles()["CONV_RN"]
    p = Weights.random([[16, 3]] * 2, [32, 32, 2], architecture="mccnn-paper", seed=6)
    paper = PaperCost(ctx, p, tiles={"RN": 4, "CONV_RN": 16})
    assert paper.stack.rn == paper.rn == 4
