"""mccnn_cl.imageops: the one gray conversion and the one standardisation."""

import cv2
import numpy as np
import pytest

from mccnn_cl.errors import InputError
from mccnn_cl.imageops import image_stats, luminance, standardise, to_gray, unit_float64
from mccnn_cl.io import read_image

from conftest import POISON


@pytest.fixture(scope="module")
def kitti_bgr(shared_data):
    return read_image(shared_data / "kitti2015" / "training" / "image_2" / "000000_10.png")


def test_to_gray_scales_and_converts(kitti_bgr):
    u8 = cv2.cvtColor(kitti_bgr, cv2.COLOR_BGR2GRAY)
    g = to_gray(kitti_bgr, "left")
    assert g.dtype == np.float32 and g.shape == u8.shape
    np.testing.assert_array_equal(g, u8.astype(np.float32) / np.float32(255))
    np.testing.assert_array_equal(luminance(kitti_bgr), u8)  # in the input's own type
    np.testing.assert_array_equal(to_gray(u8), g)
    np.testing.assert_array_equal(to_gray(u8[:, :, None]), g)
    bgra = np.dstack([kitti_bgr, np.full(u8.shape, 7, np.uint8)])
    np.testing.assert_array_equal(to_gray(bgra), g)  # alpha ignored
    u16 = u8.astype(np.uint16) * 257
    np.testing.assert_array_equal(to_gray(u16), (u16.astype(np.float32) / np.float32(65535)))
    np.testing.assert_array_equal(to_gray(g), g)  # float in [0, 1]: as is
    for bad, words in [(g + 1, r"\[0, 1\]"), (np.full((4, 4), np.nan, np.float32), "NaN"),
                       (u8.astype(np.int32), "dtype int32"), (np.zeros((4, 4, 2), np.uint8), "shape")]:
        with pytest.raises(InputError, match=words):
            to_gray(bad, "left")


def test_standardise_on_a_real_image(kitti_bgr):
    u8 = luminance(kitti_bgr)
    s = standardise(u8)
    assert s.dtype == np.float32 and s.shape == u8.shape
    # integer images are brought to [0, 1] as to_gray does: the same values, bit for bit
    np.testing.assert_array_equal(s, standardise(to_gray(u8)))
    # float64 statistics over the whole image
    a = to_gray(u8).astype(np.float64)
    np.testing.assert_array_equal(s, ((a - a.mean()) / a.std()).astype(np.float32))
    assert abs(float(s.mean())) < 1e-5 and abs(float(s.std()) - 1) < 1e-5
    np.testing.assert_array_equal(standardise(np.full((5, 6), 0.3, np.float32)), np.zeros((5, 6), np.float32))


def test_training_and_inference_standardise_alike(shared_data):
    """Training standardises the uint8 gray images it reads (train.patches); inference
    standardises the matcher's [0, 1] gray input (stages.features, the networks' input):
    on a real colour image the two are equal bit for bit (before issue 17 training took
    float32 statistics and differed in about half the pixels by an ulp)."""
    from mccnn_cl.evaluation.datasets import load_kitti2015, load_middlebury
    from mccnn_cl.costs.features import normalise as inference
    from mccnn_cl.train.patches import normalise as training

    for pair in (load_kitti2015(shared_data / "kitti2015", "000000"),
                 load_middlebury(shared_data / "middlebury" / "Cones")):
        gray_u8 = pair.gray()[0]  # what the training code standardises
        a, b = training(gray_u8), inference(to_gray(pair.left, "left"))  # what the matcher hands the network
        assert a.dtype == b.dtype == np.float32
        np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))


def test_unit_float64_is_the_scale_of_the_stats(kitti_bgr):
    """unit_float64: what standardise and image_stats work on: uint8 / uint16 as to_gray
    scales them (bit for bit), float and other types as they are, idempotent; stats of an
    integer image are those of its to_gray."""
    u8 = luminance(kitti_bgr)
    u16 = u8.astype(np.uint16) * 257
    for a in (u8, u16):
        np.testing.assert_array_equal(unit_float64(a), to_gray(a).astype(np.float64))
        assert image_stats(a) == image_stats(to_gray(a))
    f = to_gray(u8)
    np.testing.assert_array_equal(unit_float64(f), f.astype(np.float64))
    np.testing.assert_array_equal(unit_float64(unit_float64(u8)), unit_float64(u8))
    np.testing.assert_array_equal(unit_float64(u8.astype(np.int32)), u8.astype(np.float64))  # no scale known
    np.testing.assert_array_equal(standardise(u8, image_stats(u8)), standardise(f, image_stats(f)))


def test_network_cost_standardises_uint8_with_its_stats(ctx, kitti_bgr):
    """The public path that combines the two: a network cost given uint8 images and
    ``stats=`` of image_stats (as mccnn_cl.distributed gives a row tile the whole image's).
    The cost's input check (validate.as_image) must bring the pixels to the scale of the
    stats (unit_float64): the volume is then that of the to_gray images, bit for bit, with
    or without stats, and a row tile with the whole image's stats gives the whole volume's
    rows.  Before, the pixels stayed 0 .. 255 against a mean and std of 0 .. 1: costs off
    by up to 0.97, and 2e-7 apart without stats."""
    from mccnn_cl.costs.network import NetworkCost
    from mccnn_cl.weights import Weights

    gray = luminance(kitti_bgr)
    y0, x0 = gray.shape[0] // 2, gray.shape[1] // 2
    L, R = gray[y0:y0 + 24, x0:x0 + 40], gray[y0:y0 + 24, x0 + 3:x0 + 43]
    assert L.dtype == np.uint8 and L.std() > 5 and R.std() > 5
    net = NetworkCost(ctx, Weights.random([[8, 3], [12, 3], [12, 1]], [16, 16, 2], seed=3))  # patch 5
    D, P = 6, net.patch
    h, w = L.shape[0] - P + 1, L.shape[1] - P + 1

    def volume(left, right, stats=None):
        out = ctx.empty(D * h * w * 4, "poisoned volume")
        ctx.fill(out, POISON, D * h * w * 4)
        net(left, right, D, out=out, stats=stats)
        v = ctx.from_device(out, (D, h, w))
        assert not np.any(v == POISON)
        return v

    fL, fR = to_gray(L), to_gray(R)
    want = volume(fL, fR, (image_stats(fL), image_stats(fR)))
    u8_stats = (image_stats(L), image_stats(R))
    np.testing.assert_array_equal(volume(L, R, u8_stats).view(np.uint32), want.view(np.uint32))
    np.testing.assert_array_equal(net.to_host(L, R, D, stats=u8_stats).view(np.uint32), want.view(np.uint32))
    np.testing.assert_array_equal(volume(L, R).view(np.uint32), volume(fL, fR).view(np.uint32))
    # a row tile standardised with the whole image's statistics: the whole volume's rows, to
    # float32 rounding.  Where the conv layers run by Winograd's F(2x2, 3x3) (on a device whose
    # vectors hold 8 floats, these 8- and 12-channel layers) a crop places the tile grid at its
    # own rows (the tiled paths pass their row down; this call cannot), and sums ordered
    # otherwise differ by ~12 ulp (a Zen 3); the bug this guards against was off by up to 0.97
    r0, r1 = 4, 14
    tile = net.to_host(L[r0:r1 + P - 1], R[r0:r1 + P - 1], D, stats=u8_stats)
    np.testing.assert_allclose(tile, want[:, r0:r1], rtol=1e-5, atol=1e-6)


def test_big_endian_uint16_is_read_as_uint16():
    """A '>u2' image (a big-endian file read as is) was refused with a message
    listing uint16 as supported: it is converted to native order first."""
    rng = np.random.default_rng(4)
    u16 = rng.integers(0, 65536, (20, 30, 3), dtype=np.uint16)
    big = u16.astype(">u2")
    assert big.dtype.byteorder == ">" and not big.dtype.isnative
    np.testing.assert_array_equal(to_gray(big), to_gray(u16))
    np.testing.assert_array_equal(luminance(big), luminance(u16))
    np.testing.assert_array_equal(unit_float64(big), unit_float64(u16))
    np.testing.assert_array_equal(standardise(big), standardise(u16))
    np.testing.assert_array_equal(to_gray(u16[:, :, 0].astype(">u2"), bit_depth=16),
                                  to_gray(u16[:, :, 0], bit_depth=16))


def test_big_endian_pair_through_the_matcher(ctx):
    rng = np.random.default_rng(5)
    left = rng.integers(0, 65536, (30, 48), dtype=np.uint16)
    right = np.roll(left, -3, axis=1)
    from mccnn_cl.pipeline import StereoMatcher

    m = StereoMatcher(cost="census", max_disparity=8, device=ctx)
    np.testing.assert_array_equal(m.compute(left.astype(">u2"), right.astype(">u2")), m.compute(left, right))


def test_low_bits_warning_names_the_callers_line():
    """The uint16 low-bits InputWarning points at the line that called to_gray."""
    import inspect
    import warnings

    from mccnn_cl.errors import InputWarning

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        line = inspect.currentframe().f_lineno + 1
        to_gray(np.full((10, 10), 4095, np.uint16))
    got = [(w.filename, w.lineno) for w in seen if issubclass(w.category, InputWarning)]
    assert got == [(__file__, line)], got
