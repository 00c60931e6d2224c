"""Determinism: same input, same device -> bit-identical output, run to run.

No kernel uses atomics or a reduction whose order depends on scheduling, so
nothing may change between runs, not even the last bit (a difference would
point at a race, an uninitialised read or a work-group-size-dependent
summation).  Compared as raw bytes, NaN cells included.  Checked twice per
stage: the same stage object called again, and a fresh ClContext (programs
rebuilt, buffers reallocated) on the same device.

Cross-implementation agreement (PoCL vs Intel's runtime) is measured by
``scripts/compare_impls.py`` and reported in docs/portability.md: different
compilers may contract/reorder float operations, so it is not bit-exact.
"""

import pytest
import cv2
import numpy as np

from mccnn_cl.opencl.context import ClContext
from mccnn_cl.costs.network import NetworkCost
from mccnn_cl.weights import Weights


def _real_crop(shared_data, h, w, y0=100, x0=120):
    d = shared_data / "middlebury" / "Tsukuba"
    left = cv2.imread(str(d / "im0.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(d / "im1.png"), cv2.IMREAD_GRAYSCALE)
    assert left is not None and right is not None, f"cannot read Tsukuba from {d}"
    left = left[y0:y0 + h, x0:x0 + w].astype(np.float32) / 255.0
    right = right[y0:y0 + h, x0:x0 + w].astype(np.float32) / 255.0
    assert np.ptp(left) > 0.1 and np.ptp(right) > 0.1, "crop is (nearly) constant"
    return left, right


def _same_bits(a: np.ndarray, b: np.ndarray, what: str) -> None:
    assert a.shape == b.shape and a.dtype == b.dtype, what
    if a.tobytes() != b.tobytes():
        diff = a.view(np.uint32) != b.view(np.uint32)
        idx = np.argwhere(diff)[:5].tolist()
        raise AssertionError(f"{what}: {int(diff.sum())} of {a.size} values differ between runs, "
                             f"first at {idx}")


@pytest.mark.slow
def test_network_cost_volume_is_bit_identical(ctx, shared_data):
    # a mid-sized random net (2 hidden layers of 48, 16 maps): more than one
    # register tile per work-item and several tiles per disparity
    w = Weights.random(conv_layers=[[16, 3], [16, 3], [16, 3], [16, 3]], fc_layers=[48, 48, 48, 2], seed=7)
    left, right = _real_crop(shared_data, 41, 67)
    D = 16
    net = NetworkCost(ctx, w)
    first = net.compute(left, right, D)
    assert np.isfinite(first[:, :, D:]).all() and np.ptp(first[:, :, D:]) > 0.01
    _same_bits(first, net.compute(left, right, D), "C_CNN, same stage object")

    fresh = ClContext(ctx.device)
    try:
        _same_bits(first, NetworkCost(fresh, w).compute(left, right, D), "C_CNN, fresh context")
    finally:
        fresh.close()


def test_aggregation_chain_is_bit_identical(ctx, shared_data):
    """census -> cross arms -> CBCA (4 iterations): the stages with long sums."""
    from mccnn_cl.stages.cbca import CBCA
    from mccnn_cl.costs.census import CensusCost
    from mccnn_cl.stages.cross import CrossArms, max_arm

    left, right = _real_crop(shared_data, 48, 77)
    D, H, W = 12, 40, 69

    def run(c):
        d_cost = CensusCost(c)(left, right, D)
        arms_l = CrossArms(c)(c.to_device(np.ascontiguousarray(left[4:-4, 4:-4])), H, W)
        arms_r = CrossArms(c)(c.to_device(np.ascontiguousarray(right[4:-4, 4:-4])), H, W)
        out = CBCA(c, max_arm=max_arm(4))(d_cost, arms_l, arms_r, D, H, W, iterations=4, max_arm=max_arm(4))
        return c.from_device(out, (D, H, W))

    first = run(ctx)
    assert np.ptp(first[:, :, D:]) > 0.01
    _same_bits(first, run(ctx), "census + CBCA, same context")
    fresh = ClContext(ctx.device)
    try:
        _same_bits(first, run(fresh), "census + CBCA, fresh context")
    finally:
        fresh.close()


def test_stereo_matcher_census_disparity_is_bit_identical(ctx, shared_data):
    """The whole method (census cost, CBCA, SGM, disparity stages, refinement)."""
    from mccnn_cl.pipeline import StereoMatcher

    left, right = _real_crop(shared_data, 64, 96, y0=110, x0=130)
    first = StereoMatcher(max_disparity=16, device=ctx, cost="census").compute(left, right)
    assert first.shape == left.shape and np.isfinite(first).all() and np.ptp(first) > 1
    _same_bits(first, StereoMatcher(max_disparity=16, device=ctx, cost="census").compute(left, right),
               "final disparity, same context")
    fresh = ClContext(ctx.device)
    try:
        _same_bits(first, StereoMatcher(max_disparity=16, device=fresh, cost="census").compute(left, right),
                   "final disparity, fresh context")
    finally:
        fresh.close()
