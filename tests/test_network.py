"""C_CNN on the device (kernels/network_conv.cl, network_head.cl) against the
patch-by-patch reference (mccnn_cl.reference.network) and against torch.

Tolerance: every cost is a probability in [0, 1].  The kernels accumulate in
float32 (sums of up to 800 products per unit, in another order than the
float64 reference), which gives logit errors of order 1e-6..1e-5 for weights
of He scale; the softmax has slope <= 1/4, so 1e-4 absolute on the cost is
a bound with a wide margin that still catches any wrong index, weight or
layer (those move costs by 1e-2 or more).  NaN positions must match exactly.
"""

import cv2
import numpy as np
import pytest
import torch

from mccnn_cl.errors import InputError
from mccnn_cl.reference import network as ref
from mccnn_cl.costs.network import NetworkCost, normalise
from mccnn_cl.weights import Weights

from conftest import POISON

TOL = 1e-4
SMALL_CONV = [[8, 3], [12, 3], [12, 1]]          # patch 5
SMALL_CONV9 = [[6, 5], [10, 5], [10, 1]]         # patch 9, like the paper
SMALL_TILES = dict(TM=4, RM=2, RN=4, CONV_RM=3)  # many partial tiles, other vector width
SCALAR_TILES = dict(TM=3, RM=1, RN=1, CONV_RM=1)  # scalar code paths, 1-row micro-tiles

_nets = {}


def net_for(ctx, w, tiles=None, key=None):
    """NetworkCost cached per (weights key, tiles) so programs are built once per test run."""
    k = (key, repr(sorted((tiles or {}).items())))
    if key is None or k not in _nets:
        n = NetworkCost(ctx, w, tiles)
        if key is None:
            return n
        _nets[k] = n
    return _nets[k]


def run_poisoned(ctx, net, left, right, D):
    """Volume from the device, written into a buffer filled with POISON first."""
    P = net.patch
    h, w = left.shape[0] - P + 1, left.shape[1] - P + 1
    nbytes = D * h * w * 4
    d_out = ctx.empty(nbytes, "test volume")
    ctx.fill(d_out, POISON, nbytes)
    ret = net(left, right, D, out=d_out)
    assert ret is d_out
    return ctx.from_device(d_out, (D, h, w))


def check(got, expected, D, h, w):
    assert got.shape == expected.shape == (D, h, w)
    assert not np.any(got == POISON), "cells left unwritten"
    np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
    # invalid by index, x - d < 0, and nothing else
    d, _, x = np.meshgrid(np.arange(D), np.arange(h), np.arange(w), indexing="ij")
    np.testing.assert_array_equal(np.isnan(got), x < d)
    valid = ~np.isnan(expected)
    if valid.any():
        err = np.abs(got[valid] - expected[valid]).max()
        assert err <= TOL, f"max abs error {err:.3g}"
        assert np.all((got[valid] >= 0) & (got[valid] <= 1))


def random_pair(rng, H, W):
    left = rng.random((H, W)).astype(np.float32) * 255
    right = np.roll(left, -3, axis=1) + rng.normal(0, 8, (H, W)).astype(np.float32)
    assert left.std() > 0 and right.std() > 0
    return left, right


@pytest.fixture(scope="module")
def paper_weights():
    return Weights.random(seed=7)  # L1 5x5x32, L2 5x5x200, L3 1x1x200, 4 x 300, 2


def read_gray(path):
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None, f"cannot read {path}"
    return img


# -- the paper-size network --------------------------------------------------

@pytest.mark.gpu_check
def test_paper_net_random_image(ctx, paper_weights):
    rng = np.random.default_rng(1)
    left, right = random_pair(rng, 21, 34)
    net = net_for(ctx, paper_weights, key="paper")
    assert net.hp >= 300 and net.hp % net.rn == 0 and net.nhid == 3
    got = run_poisoned(ctx, net, left, right, 12)
    check(got, ref.cost_volume(paper_weights, left, right, 12), 12, 13, 26)


@pytest.mark.parametrize("crop", [
    ("kitti2015/training/image_2/000000_10.png", "kitti2015/training/image_3/000000_10.png", 180, 600),
    ("middlebury/Cones/im0.png", "middlebury/Cones/im1.png", 150, 200),
], ids=["kitti2015-000000", "middlebury-cones"])
@pytest.mark.gpu_check
@pytest.mark.slow
def test_paper_net_real_crops(ctx, paper_weights, shared_data, crop):
    lp, rp, y0, x0 = crop
    left = read_gray(shared_data / lp)[y0:y0 + 40, x0:x0 + 60]
    right = read_gray(shared_data / rp)[y0:y0 + 40, x0:x0 + 60]
    assert left.shape == (40, 60) and left.std() > 5 and right.std() > 5
    net = net_for(ctx, paper_weights, key="paper")
    D = 16
    got = run_poisoned(ctx, net, left, right, D)
    check(got, ref.cost_volume(paper_weights, left, right, D), D, 32, 52)


@pytest.mark.full_data
def test_matches_torch_model(ctx, paper_weights, shared_data, monkeypatch):
    """MCCNN.from_weights run convolutionally (features -> L4 split -> head) in torch."""
    left = read_gray(shared_data / "kitti2015/training/image_2/000001_10.png")[200:236, 300:360]
    right = read_gray(shared_data / "kitti2015/training/image_3/000001_10.png")[200:236, 300:360]
    assert left.std() > 5
    net = net_for(ctx, paper_weights, key="paper")
    D = 20
    got = run_poisoned(ctx, net, left, right, D)
    expected = ref.cost_volume_torch(paper_weights, left, right, D)
    check(got, expected, D, 28, 52)
    # in bands of 8 volume rows (4 bands): the same bits
    import mccnn_cl.costs.network as stage
    monkeypatch.setattr(stage, "BAND_BYTES", 8 * 52 * net.hp * 4)
    np.testing.assert_array_equal(run_poisoned(ctx, net, left, right, D), got)
    # and the torch module on explicit 9x9 patch pairs for a few cells
    from mccnn_cl.train.model import MCCNN
    m = MCCNN.from_weights(paper_weights)
    L, R = torch.from_numpy(normalise(left)), torch.from_numpy(normalise(right))
    cells = [(0, 0, 0), (5, 3, 17), (19, 27, 51), (19, 10, 19), (7, 20, 40)]
    pl = torch.stack([L[y:y + 9, x:x + 9] for d, y, x in cells])[:, None]
    pr = torch.stack([R[y:y + 9, x - d:x - d + 9] for d, y, x in cells])[:, None]
    with torch.no_grad():
        p_bad = torch.softmax(m(pl, pr), dim=1)[:, 0].numpy()
    np.testing.assert_allclose([got[c] for c in cells], p_bad, rtol=0, atol=TOL)


# -- small random networks, odd sizes, other tiles ----------------------------

@pytest.mark.parametrize("tiles", [None, SMALL_TILES, SCALAR_TILES], ids=["default", "small", "scalar"])
@pytest.mark.parametrize("case", [
    # conv layers, fc layers, image H x W, D
    (SMALL_CONV, [16, 16, 2], 37, 53, 16),        # odd sizes
    (SMALL_CONV9, [16, 16, 16, 2], 9, 41, 12),    # one output row
    (SMALL_CONV, [24, 10, 7, 2], 15, 20, 25),     # D >= W, uneven hidden widths
    (SMALL_CONV, [20, 2], 12, 17, 5),              # no hidden layer after L4
    ([[5, 3], [7, 3]], [9, 9, 2], 11, 29, 9),      # two conv layers
], ids=["37x53", "one-row", "D>=W", "no-hidden", "two-conv"])
@pytest.mark.gpu_check
@pytest.mark.slow
def test_small_nets(ctx, case, tiles):
    conv, fc, H, W, D = case
    w = Weights.random(conv, fc, seed=H * W)
    rng = np.random.default_rng(H + W)
    left, right = random_pair(rng, H, W)
    net = net_for(ctx, w, tiles)
    P = w.patch_size
    got = run_poisoned(ctx, net, left, right, D)
    check(got, ref.cost_volume(w, left, right, D), D, H - P + 1, W - P + 1)


@pytest.mark.gpu_check
def test_constant_images(ctx):
    w = Weights.random(SMALL_CONV, [16, 16, 2], seed=3)
    net = net_for(ctx, w, key="small")
    left = np.full((13, 19), 77.0, np.float32)
    right = np.full((13, 19), 3.0, np.float32)
    got = run_poisoned(ctx, net, left, right, 6)
    check(got, ref.cost_volume(w, left, right, 6), 6, 9, 15)
    # both images normalise to all zeros: every valid cell holds the same cost
    v = got[~np.isnan(got)]
    assert np.ptp(v) == 0


@pytest.mark.slow
def test_compute_progress_and_chunks(ctx, monkeypatch):
    import mccnn_cl.costs.network as stage
    w = Weights.random(SMALL_CONV, [16, 16, 2], seed=4)
    net = net_for(ctx, w, key="small4")
    rng = np.random.default_rng(9)
    left, right = random_pair(rng, 14, 31)
    monkeypatch.setattr(stage, "CHUNK_CELLS", 10 * 27 * 3)  # 3 disparities per launch
    calls = []
    got = net.compute(left, right, 10)  # no progress callback
    got2 = ctx.from_device(net(left, right, 10, progress=lambda done, total: calls.append((done, total))),
                           (10, 10, 27))
    assert calls == [(3, 10), (6, 10), (9, 10), (10, 10)]
    expected = ref.cost_volume(w, left, right, 10)
    check(got, expected, 10, 10, 27)
    np.testing.assert_array_equal(got, got2)
    # bands of 3 volume rows (the last one 1 row): seams exact, progress still in disparities
    monkeypatch.setattr(stage, "BAND_BYTES", 3 * 27 * net.hp * 4)
    assert net.band_rows(10, 27) == 3
    calls.clear()
    got3 = ctx.from_device(net(left, right, 10, progress=lambda done, total: calls.append((done, total))),
                           (10, 10, 27))
    assert [c[1] for c in calls] == [10] * len(calls) and calls[-1] == (10, 10)
    assert all(a[0] <= b[0] for a, b in zip(calls, calls[1:]))
    check(got3, expected, 10, 10, 27)
    np.testing.assert_array_equal(got3, got)  # per-cell arithmetic does not depend on the band


def test_normalise():
    img = np.arange(12, dtype=np.uint8).reshape(3, 4)
    n = normalise(img)
    assert n.dtype == np.float32
    np.testing.assert_allclose(n.mean(), 0, atol=1e-6)
    np.testing.assert_allclose(n.std(), 1, atol=1e-6)
    z = normalise(np.full((5, 5), 9.0))
    assert z.dtype == np.float32 and np.all(z == 0)


def test_input_errors(ctx):
    w = Weights.random(SMALL_CONV9, [16, 16, 2], seed=5)  # patch 9
    net = net_for(ctx, w, key="errors")
    ok = np.random.default_rng(0).random((12, 20)).astype(np.float32)
    cases = [
        (ok[0], ok, 4),                                   # not 2-D
        (np.zeros((2, 12, 20)) + ok, ok, 4),              # 3 dims, 20 "channels"
        (np.dstack([ok, ok, ok]), np.dstack([ok] * 3), 4),  # colour into a gray network
        (ok, ok[:, :19], 4),                              # shapes differ
        (ok[:8], ok[:8], 4),                              # height < patch
        (ok[:, :8], ok[:, :8], 4),                        # width < patch
        (ok, ok, 0),                                      # max_disparity < 1
        (ok, ok, -3),
        (ok, ok, 2.5),                                    # not an integer
        (np.where(ok > 0.5, np.nan, ok), ok, 4),          # NaN pixel
        (ok, np.where(ok > 0.5, np.inf, ok), 4),          # inf pixel
        (ok.astype(str), ok, 4),                          # not numeric
    ]
    for left, right, D in cases:
        with pytest.raises(InputError):
            net(left, right, D)
    # a volume larger than one device allocation is refused before allocating
    big = np.random.default_rng(1).random((2000, 2000)).astype(np.float32)
    D = ctx.max_alloc // (1992 * 1992 * 4) + 1
    with pytest.raises(InputError, match="cost volume"):
        net(big, big, D)


@pytest.mark.parametrize("max_rows", [1, 3, 100])
@pytest.mark.slow
def test_to_host_bands_identical(ctx, max_rows):
    """The host-resident volume (computed band by band into a band-sized device
    buffer, for volumes larger than the device) equals the one-buffer volume bit
    for bit: same kernels, band seams exact."""
    w = Weights.random(SMALL_CONV9, [16, 16, 2], seed=11)
    net = NetworkCost(ctx, w)
    rng = np.random.default_rng(12)
    left, right = random_pair(rng, 23, 37)
    D = 9
    h, wd = 23 - net.patch + 1, 37 - net.patch + 1
    whole = run_poisoned(ctx, net, left, right, D)
    check(whole, ref.cost_volume(w, left, right, D), D, h, wd)
    got = net.to_host(left, right, D, max_bytes=max_rows * D * wd * 4)
    assert got.shape == (D, h, wd) and got.dtype == np.float32
    np.testing.assert_array_equal(got, whole)  # NaN positions included
    assert np.isnan(got[D - 1, :, :D - 1]).all() and np.isfinite(got[0]).all()
    with pytest.raises(InputError, match="does not fit"):
        net.to_host(left, right, D, max_bytes=D * wd * 4 - 1)


def test_flops_count(ctx, paper_weights):
    """NetworkCost.flops: the paper's per-cell head is 300 adds (L4 = A + B) +
    3 x 300 x 300 + 300 x 2 multiply-adds; valid cells are x >= d on the 9x9-valid domain."""
    net = NetworkCost(ctx, paper_weights)
    f = net.flops(20, 30, 5)
    h, w = 20 - 8, 30 - 8
    assert f["valid_cells"] == sum(1 for d in range(5) for y in range(h) for x in range(w) if x >= d)
    assert f["head"] == f["valid_cells"] * (300 + 2 * 3 * 300 * 300 + 2 * 300 * 2)
    conv = 2 * 2 * (26 * 16 * 25 * 1 * 32 + 22 * 12 * 25 * 32 * 200 + 22 * 12 * 200 * 200)
    assert f["features"] == conv + 2 * 2 * 12 * 22 * 200 * 300
    assert f["total"] == f["features"] + f["head"]


# -- settings that travel with the network (StereoMatcher) --------------------

@pytest.mark.slow
def test_settings_travel_with_weights(ctx):
    """Weights.stereo applies first, the caller's overrides win; fst's settings
    (no CBCA) run without cross arms; the cost class follows the architecture."""
    from mccnn_cl.pipeline import StereoMatcher
    from mccnn_cl.settings import authors_settings
    from mccnn_cl.costs.fst import FstCost

    w = Weights.random([[8, 3]] * 2, architecture="mccnn-fst", seed=2)
    w.meta["stereo"] = authors_settings("mccnn-fst", "kitti")
    sm = StereoMatcher(weights=w, max_disparity=8, device=ctx, sgm_pi2=40.0)
    assert isinstance(sm.cost, FstCost) and sm.margin == 2
    assert sm.params.sgm_pi2 == 40.0                      # the caller wins
    assert sm.params.sgm_pi1 == 4.0 and sm.params.sgm_tau_so == 0.02  # the network's
    assert sm.params.intensity_scale == "standardised" and sm.params.cbca_iterations == 0
    rng = np.random.default_rng(0)
    left = rng.random((24, 40)).astype(np.float32)
    right = np.roll(left, -2, axis=1)
    res = sm.compute(left, right, timings=True)
    assert res.disparity.shape == (24, 40) and np.isfinite(res.disparity).all()
    assert "cross" not in res.timings and "cross_R" not in res.timings
    # the thresholds compare the standardised images
    S_L, _ = sm._threshold_images(left, right)
    np.testing.assert_allclose(S_L, normalise(left))
    # without settings in the file: the paper's defaults, unit scale
    w.meta.pop("stereo")
    sm = StereoMatcher(weights=w, max_disparity=8, device=ctx)
    assert sm.params.intensity_scale == "unit" and sm.params.sgm_pi2 == 32.0
    assert sm._threshold_images(left, right)[0] is left


def test_settings_errors(ctx):
    from mccnn_cl.errors import WeightsError
    from mccnn_cl.pipeline import Hyperparameters, StereoMatcher

    w = Weights.random([[8, 3]], [4, 2], seed=1)
    w.meta["stereo"] = {"sgm_pi9": 1.0}
    with pytest.raises(WeightsError, match="sgm_pi9"):
        StereoMatcher(weights=w, max_disparity=8, device=ctx)
    with pytest.raises(InputError, match="intensity_scale"):
        Hyperparameters(intensity_scale="0..255")


@pytest.mark.full_data
def test_published_fst_file_through_matcher(ctx, shared_data):
    """A .t7 path goes through weights.resolve and the importer: the fst cost
    with the authors' KITTI settings, which the caller can still override."""
    from mccnn_cl.pipeline import StereoMatcher
    from mccnn_cl.costs.fst import FstCost

    path = shared_data.parent / "models" / "net_kitti_fast_-a_train_all.t7"
    assert path.exists(), path
    sm = StereoMatcher(weights=str(path), max_disparity=16, device=ctx, blur_sigma=3.0)
    assert isinstance(sm.cost, FstCost) and sm.margin == 4
    assert (sm.params.sgm_pi1, sm.params.sgm_pi2, sm.params.sgm_tau_so) == (4.0, 55.72, 0.02)
    assert sm.params.blur_sigma == 3.0 and sm.params.intensity_scale == "standardised"
