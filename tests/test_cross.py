"""Cross arms: kernels/cross.cl against mccnn_cl.reference.aggregation.cross_arms.

Arms are integers: compared exactly.  The outputs are poisoned (0xEE bytes,
an arm length no input here can produce: eta <= 30) before every launch.
"""

import cv2
import numpy as np
import pytest

from mccnn_cl.errors import InputError
from mccnn_cl.reference.aggregation import cross_arms
from mccnn_cl.stages.cross import CrossArms, arms_from_device, max_arm

POISON_BYTE = 0xEE


def run_arms(ctx, img, **kw):
    img = np.ascontiguousarray(img, dtype=np.float32)
    H, W = img.shape
    d_arms = ctx.empty(4 * H * W)
    ctx.fill(d_arms, POISON_BYTE, 4 * H * W, dtype=np.uint8)
    CrossArms(ctx)(ctx.to_device(img), H, W, out=d_arms, **kw)
    return arms_from_device(ctx, d_arms, H, W)


def check(ctx, img, **kw):
    got = run_arms(ctx, img, **kw)
    want = cross_arms(img, **kw)
    np.testing.assert_array_equal(got, want)
    return got


def real_crop(shared_data, rel, y0, x0, h, w):
    img = cv2.imread(str(shared_data / rel), cv2.IMREAD_GRAYSCALE)
    assert img is not None, rel
    return (img[y0:y0 + h, x0:x0 + w].astype(np.float32) / 255.0)


@pytest.mark.parametrize("shape", [(37, 53), (1, 41), (29, 1), (1, 1), (8, 8)])
@pytest.mark.parametrize("include_neighbor", [False, True])
def test_random_images(ctx, shape, include_neighbor):
    rng = np.random.default_rng(7)
    # a coarse image with small noise, so arms of every length occur
    img = (np.repeat(np.repeat(rng.random((shape[0] // 3 + 1, shape[1] // 3 + 1)), 3, 0), 3, 1)
           [:shape[0], :shape[1]] + 0.02 * rng.random(shape)).astype(np.float32)
    got = check(ctx, img, tau=0.0442, eta=4, include_neighbor=include_neighbor)
    if shape[0] * shape[1] > 100:
        assert len(np.unique(got)) >= 3  # non-trivial: several arm lengths occur


@pytest.mark.parametrize("rel", ["middlebury/Cones/im0.png", "middlebury/Cones/im1.png",
                                 "kitti2015/training/image_2/000000_10.png",
                                 "kitti2015/training/image_3/000000_10.png"])
def test_real_images(ctx, shared_data, rel):
    img = real_crop(shared_data, rel, 100, 200, 45, 61)
    assert img.std() > 0.01
    got = check(ctx, img)
    assert got.max() == 3 and got.min() == 0
    check(ctx, img, tau=0.1, eta=9, include_neighbor=True)


def test_constant_image_arms_hit_eta_and_borders(ctx):
    H, W = 13, 17
    got = check(ctx, np.full((H, W), 0.5, np.float32), eta=5)
    x = np.arange(W)
    y = np.arange(H)[:, None]
    np.testing.assert_array_equal(got[..., 0], np.broadcast_to(np.minimum(x, 4), (H, W)))
    np.testing.assert_array_equal(got[..., 1], np.broadcast_to(np.minimum(W - 1 - x, 4), (H, W)))
    np.testing.assert_array_equal(got[..., 2], np.broadcast_to(np.minimum(y, 4), (H, W)))
    np.testing.assert_array_equal(got[..., 3], np.broadcast_to(np.minimum(H - 1 - y, 4), (H, W)))


def test_long_arms_and_edge_parameters(ctx):
    img = np.full((9, 300), 0.25, np.float32)
    got = check(ctx, img, eta=256)  # arms up to 255, capped by the byte storage
    assert got[..., 1].max() == 255
    # eta = 1 or 0: no arm at all (unless the neighbour is forced in)
    assert check(ctx, img[:, :20], eta=1).max() == 0
    got = check(ctx, img[:, :20], eta=0, include_neighbor=True)
    assert got.max() == 1


def test_checkerboard_stops_at_first_failure(ctx):
    img = (np.indices((11, 12)).sum(0) % 2).astype(np.float32)
    got = check(ctx, img, eta=6)
    assert got.max() == 0
    got = check(ctx, img, eta=6, include_neighbor=True)
    # the forced neighbour (k = 1, different value), then k = 2 has the centre's value and is
    # accepted, k = 3 differs and stops the arm: length 2 except near the borders
    x = np.arange(12)
    np.testing.assert_array_equal(got[..., 0], np.broadcast_to(np.minimum(x, 2), (11, 12)))
    np.testing.assert_array_equal(got[..., 1], np.broadcast_to(np.minimum(11 - x, 2), (11, 12)))


def test_bad_eta(ctx):
    d = ctx.to_device(np.zeros((2, 2), np.float32))
    with pytest.raises(InputError):
        CrossArms(ctx)(d, 2, 2, eta=300)
    with pytest.raises(InputError):
        CrossArms(ctx)(d, 0, 2)
    assert max_arm(4) == 3 and max_arm(1, True) == 1 and max_arm(1000) == 255
