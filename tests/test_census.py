"""Census cost kernel against its numpy twin (exact: popcount / 80 in float32
is the same correctly rounded division in both)."""

import cv2
import numpy as np
import pytest

from mccnn_cl.errors import InputError
from mccnn_cl.reference import disparity as ref
from mccnn_cl.costs.census import CensusCost

from conftest import POISON


def run_census(ctx, left, right, D, shape=None):
    H, W = left.shape[0] - 8, left.shape[1] - 8
    out = ctx.empty(D * H * W * 4, "poisoned")
    ctx.fill(out, POISON, D * H * W * 4)
    d = CensusCost(ctx, launch_shape=shape)(left, right, D, out=out)
    return ctx.from_device(d, (D, H, W))


def same_nan(a, b):
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_array_equal(a[~np.isnan(a)], b[~np.isnan(b)])


# launch shapes of the cost kernel (RULES "census_cost_launch"): all levels per
# work-item (CPU-shaped devices), one, three (a partial last chunk of levels)
SHAPES = [(0, (16, 1, 1)), (1, None), (3, (2, 2, 2))]


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("Hi,Wi,D", [(37, 53, 16), (9, 30, 7), (12, 14, 20), (10, 60, 40)])
def test_census_random(ctx, Hi, Wi, D, shape):
    rng = np.random.default_rng(Hi * Wi)
    left = (rng.integers(0, 8, (Hi, Wi)) / 7).astype(np.float32)  # few levels: equal neighbours occur
    right = (rng.integers(0, 8, (Hi, Wi)) / 7).astype(np.float32)
    C = run_census(ctx, left, right, D, shape)
    expect = ref.census_cost(left, right, D)
    same_nan(C, expect)
    valid = ~np.isnan(C)
    assert valid.any() and C[valid].min() >= 0 and C[valid].max() <= 1
    for d in range(D):  # NaN exactly where x - d < 0
        assert np.isnan(C[d, :, :d]).all() and not np.isnan(C[d, :, d:]).any()


def test_census_every_count_is_the_correctly_rounded_quotient(ctx):
    """Every Hamming count 0..80 occurs (the right image is the left one with a growing share
    of its pixels inverted, row by row) and each cost is exactly float32(count) / float32(80):
    the kernel must not use a division that OpenCL lets be inexact (NVIDIA's is 1 ulp off)."""
    rng = np.random.default_rng(80)
    H, W = 60, 60
    left = rng.random((H, W), dtype=np.float32)
    right = np.where(rng.random((H, W)) < np.linspace(0, 1, H)[:, None], 1 - left, left).astype(np.float32)
    C = run_census(ctx, left, right, 3)
    expect = ref.census_cost(left, right, 3)
    counts = np.round(expect[~np.isnan(expect)] * 80).astype(int)
    assert set(counts.tolist()) == set(range(81))
    same_nan(C, expect)
    np.testing.assert_array_equal(np.float32(counts) / np.float32(80), expect[~np.isnan(expect)])


def test_census_real(ctx, shared_data):
    d = shared_data / "middlebury" / "Tsukuba"
    left = cv2.imread(str(d / "im0.png"), cv2.IMREAD_GRAYSCALE)[100:141, 150:211].astype(np.float32) / 255
    right = cv2.imread(str(d / "im1.png"), cv2.IMREAD_GRAYSCALE)[100:141, 150:211].astype(np.float32) / 255
    assert left.std() > 0.05
    C = run_census(ctx, left, right, 16)
    same_nan(C, ref.census_cost(left, right, 16))
    # identical images: zero cost at d = 0
    C0 = run_census(ctx, left, left, 4)
    assert (C0[0] == 0).all()


def test_census_constant_image_and_errors(ctx):
    c = np.full((9, 9), 0.5, np.float32)
    C = run_census(ctx, c, c, 1)  # smallest image: a 1 x 1 domain
    assert C.shape == (1, 1, 1) and C[0, 0, 0] == 0
    with pytest.raises(InputError):
        CensusCost(ctx)(np.zeros((8, 20), np.float32), np.zeros((8, 20), np.float32), 4)
    with pytest.raises(InputError):
        CensusCost(ctx)(np.zeros((10, 20), np.float32), np.zeros((10, 21), np.float32), 4)
