"""MC-CNN-acrt on the device (PaperCost's kernels with network_head.cl's
NOUT=1 sigmoid output) against mccnn_cl.reference.network.cost_volume.

Tolerance: costs are sigmoid outputs in [0, 1] with slope <= 1/4; float32
accumulation over up to 9 * 112 conv products and 384 fc products gives
logit errors ~1e-5 at He scale, so 1e-4 absolute has margin and still
catches a wrong output layer (softmax of one logit would be 1 everywhere),
a missing ReLU or a wrong index (errors of 1e-2 or more).
"""

import cv2
import numpy as np
import pytest

from mccnn_cl.errors import WeightsError
from mccnn_cl.reference import network as ref
from mccnn_cl.costs.registry import make_cost
from mccnn_cl.costs.network import AcrtCost, PaperCost
from mccnn_cl.weights import Weights

from helpers import random_pair, run_poisoned

TOL = 1e-4


def check(got, expected):
    D, h, w = expected.shape
    d, _, x = np.meshgrid(np.arange(D), np.arange(h), np.arange(w), indexing="ij")
    np.testing.assert_array_equal(np.isnan(got), x < d)
    v = ~np.isnan(expected)
    err = np.abs(got[v].astype(np.float64) - expected[v]).max()
    assert err <= TOL, f"max abs error {err:.3g}"
    assert np.all((got[v] >= 0) & (got[v] <= 1))
    assert np.ptp(got[v]) > 1e-3  # not a constant (e.g. a softmax of one logit)


@pytest.mark.parametrize("tiles", [None, dict(TM=4, RM=2, RN=4, CONV_RM=3)], ids=["default", "small"])
@pytest.mark.parametrize("case", [
    ([[16, 3]] * 4, [24, 24, 1], 37 + 8, 53 + 8, 16),     # 37 x 53 volume, D = 16
    ([[9, 3], [7, 3]], [13, 1], 11, 30, 9),               # no hidden layer, odd widths
    ([[8, 3]] * 5, [16, 16, 16, 1], 15, 19, 12),          # Middlebury's depth (patch 11), D > W
], ids=["37x53-D16", "no-hidden", "mb-depth-D>W"])
def test_random_images(ctx, case, tiles):
    conv, fc, H, W, D = case
    w = Weights.random(conv, fc, architecture="mccnn-acrt", seed=H + W)
    left, right = random_pair(np.random.default_rng(H * W), H, W)
    cost = AcrtCost(ctx, w, tiles=tiles)
    assert cost.nout == 1
    check(run_poisoned(ctx, cost, left, right, D), ref.cost_volume(w, left, right, D))


@pytest.mark.slow
def test_real_crop_default_layers(ctx, shared_data):
    """KITTI crop through the default acrt sizes (4 x 112 maps, fc 4 x 384, 1)."""
    lp, rp = "kitti2015/training/image_2/000000_10.png", "kitti2015/training/image_3/000000_10.png"
    left = cv2.imread(str(shared_data / lp), cv2.IMREAD_GRAYSCALE)[180:205, 600:650]
    right = cv2.imread(str(shared_data / rp), cv2.IMREAD_GRAYSCALE)[180:205, 600:650]
    assert left.std() > 5
    w = Weights.random(architecture="mccnn-acrt", seed=3)
    cost = make_cost(ctx, w)
    assert isinstance(cost, AcrtCost) and cost.margin == 4
    check(run_poisoned(ctx, cost, left, right, 10), ref.cost_volume(w, left, right, 10))


def test_architecture_checked(ctx):
    with pytest.raises(WeightsError):
        AcrtCost(ctx, Weights.random([[8, 3]], [4, 2], seed=1))
    with pytest.raises(WeightsError):
        PaperCost(ctx, Weights.random([[8, 3]], [4, 1], architecture="mccnn-acrt", seed=1))
    f = AcrtCost(ctx, Weights.random([[8, 3]], [4, 1], architecture="mccnn-acrt", seed=1)).flops(10, 20, 5)
    assert f["total"] == f["features"] + f["head"] > 0
