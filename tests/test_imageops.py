"""mccnn_cl.imageops: the one gray conversion and the one standardisation."""

import cv2
import numpy as np
import pytest

from mccnn_cl.errors import InputError
from mccnn_cl.imageops import luminance, standardise, to_gray
from mccnn_cl.io import read_image


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
