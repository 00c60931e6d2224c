"""Calibration parsing on the real files, depth formula, PLY round trips, visualisation, SGBM."""

import os

import numpy as np
import pytest

from mccnn_cl import depth
from mccnn_cl.evaluation.baseline import sgbm, sgbm_parameters
from mccnn_cl.errors import InputError
from mccnn_cl.io import read_image
from mccnn_cl.visualize import colorize, colorize_with_legend, error_image, legend_bar


def test_kitti2015_calib_cam_to_cam(shared_data):
    c = depth.read_calib(shared_data / "kitti2015/training/calib_cam_to_cam/000000.txt")
    assert c.kind == "kitti_cam_to_cam" and c.unit == "m"
    assert c.focal == pytest.approx(721.5377)
    # baseline from P_rect_02/03: (44.85728 - (-339.5242)) / 721.5377, the known ~0.54 m KITTI rig
    assert c.baseline == pytest.approx((44.85728 + 339.5242) / 721.5377, rel=1e-6)
    assert 0.50 < c.baseline < 0.56
    assert c.doffs == pytest.approx(0.0)
    assert (c.cx, c.cy) == (pytest.approx(609.5593), pytest.approx(172.854))
    assert (c.width, c.height) == (1242, 375)
    # gray cameras 0/1 of the same file: P_rect_01[0,3] = -387.5744 -> 0.537 m
    c01 = depth.read_calib(shared_data / "kitti2015/training/calib_cam_to_cam/000000.txt", cameras=(0, 1))
    assert c01.baseline == pytest.approx(387.5744 / 721.5377, rel=1e-6)


@pytest.mark.full_data
def test_middlebury_calib_without_focal(shared_data):
    c = depth.read_calib(shared_data / "middlebury/Cones/calib.txt")
    assert (c.width, c.height, c.ndisp) == (450, 375, 80)
    assert not c.has_depth
    with pytest.raises(InputError, match="no focal length"):
        depth.disparity_to_depth(np.ones((2, 2)), c)


def test_middlebury_calib_full(tmp_path):
    p = tmp_path / "calib.txt"
    p.write_text("cam0=[3979.911 0 1244.772; 0 3979.911 1019.507; 0 0 1]\n"
                 "cam1=[3979.911 0 1369.115; 0 3979.911 1019.507; 0 0 1]\n"
                 "doffs=124.343\nbaseline=193.001\nwidth=2964\nheight=1988\nndisp=270\nisint=0\n")
    c = depth.read_calib(p)
    assert c.focal == pytest.approx(3979.911) and c.baseline == pytest.approx(193.001)
    assert c.doffs == pytest.approx(124.343) and c.ndisp == 270 and c.unit == "mm"
    z = depth.disparity_to_depth(np.array([[100.0, np.nan, -124.343]], np.float32), c)
    assert z[0, 0] == pytest.approx(3979.911 * 193.001 / (100 + 124.343), rel=1e-6)
    assert np.isnan(z[0, 1]) and np.isnan(z[0, 2])  # invalid, and d + doffs = 0


def test_bad_calib_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        depth.read_calib(tmp_path / "missing.txt")
    p = tmp_path / "x.txt"
    p.write_text("hello world\n")
    with pytest.raises(InputError, match="not a KITTI"):
        depth.read_calib(p)
    p.write_text("P_rect_02: 1 2 3\nP_rect_03: 1 2 3\n")
    with pytest.raises(InputError, match="12"):
        depth.read_calib(p)


def test_depth_and_points_formula():
    c = depth.Calibration(focal=500.0, baseline=0.5, doffs=0.0, cx=1.0, cy=0.5, unit="m")
    disp = np.array([[50.0, 25.0, 0.0],
                     [np.inf, 10.0, 5.0]], np.float32)
    z = depth.disparity_to_depth(disp, c)
    np.testing.assert_allclose(z[0, :2], [5.0, 10.0])
    assert np.isnan(z[0, 2]) and np.isnan(z[1, 0])  # d = 0 (at infinity) and invalid
    color = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)  # BGR
    pts, rgb = depth.point_cloud(disp, c, color)
    assert len(pts) == 4
    # pixel (x=0, y=0): z = 5, X = (0 - 1) * 5 / 500, Y = (0 - 0.5) * 5 / 500
    np.testing.assert_allclose(pts[0], [-0.01, -0.005, 5.0], rtol=1e-6)
    np.testing.assert_array_equal(rgb[0], color[0, 0, ::-1])
    pts2, _ = depth.point_cloud(disp, c, max_depth=20)
    assert len(pts2) == 2  # z = 50 and 100 dropped


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip(tmp_path, binary):
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(57, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (57, 3)).astype(np.uint8)
    path = tmp_path / "cloud.ply"
    depth.write_ply(path, pts, rgb, binary=binary)
    head = path.read_bytes()[:200]
    assert (b"binary_little_endian" if binary else b"format ascii") in head
    p2, c2 = depth.read_ply(path)
    np.testing.assert_allclose(p2, pts, rtol=1e-5, atol=1e-6)  # ASCII keeps 6 significant digits
    np.testing.assert_array_equal(c2, rgb)
    assert [f.name for f in tmp_path.iterdir()] == ["cloud.ply"]  # no temporary left behind
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0600


def test_truncated_ply_is_rejected(tmp_path):
    path = tmp_path / "c.ply"
    depth.write_ply(path, np.zeros((10, 3)), None)
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(InputError, match="truncated"):
        depth.read_ply(path)


def test_colorize_and_legend():
    d = np.array([[0.0, 10.0], [np.nan, 20.0]], np.float32)
    img = colorize(d, 0, 20)
    assert img.shape == (2, 2, 3) and img.dtype == np.uint8
    np.testing.assert_array_equal(img[1, 0], [0, 0, 0])  # invalid is black
    assert not np.array_equal(img[0, 0], img[1, 1])
    bar = legend_bar(200, 0, 63)
    assert bar.shape[1] == 200 and (bar < 128).any()  # ticks and labels drawn
    with_legend = colorize_with_legend(np.zeros((30, 40), np.float32), 0, 10)
    assert with_legend.shape[0] > 30 and with_legend.shape[1] >= 160
    err = error_image(np.array([[1.0, 9.0, np.nan]]), np.array([[1.0, 1.0, 2.0]]), 3.0)
    np.testing.assert_array_equal(err[0, 0], [0, 170, 0])
    assert err[0, 1, 2] > 127 and err[0, 1, 1] == 0
    np.testing.assert_array_equal(err[0, 2], [255, 0, 255])


def test_sgbm_on_tsukuba(shared_data):
    left = read_image(shared_data / "middlebury/Tsukuba/im0.png", gray=True)
    right = read_image(shared_data / "middlebury/Tsukuba/im1.png", gray=True)
    disp = sgbm(left, right, 20)
    assert disp.dtype == np.float32 and disp.shape == left.shape
    assert np.isnan(disp[:, :10]).all()  # SGBM's invalid left border
    fin = disp[np.isfinite(disp)]
    assert fin.min() >= 0 and fin.max() <= 19  # range 20 (32 for OpenCV) clipped back to 0..19
    p = sgbm_parameters(20, channels=3)
    assert p["numDisparities"] == 32 and p["P1"] == 8 * 3 * 25 and p["P2"] == 32 * 3 * 25
    with pytest.raises(InputError):
        sgbm(left, right[:, :-1], 20)
    with pytest.raises(InputError, match="width"):
        sgbm(left[:, :30], right[:, :30], 20)


def test_point_cloud_colours_scaled_as_to_gray():
    """Colours are brought to uint8 on to_gray's scale (a plain cast wrapped
    uint16 and truncated [0, 1] floats to 0: a black cloud); other types are
    refused."""
    c = depth.Calibration(focal=500.0, baseline=0.5, cx=1.0, cy=1.0, unit="m")
    disp = np.full((3, 4), 20.0, np.float32)
    rng = np.random.default_rng(2)
    bgr = rng.integers(0, 256, (3, 4, 3), dtype=np.uint8)
    _, want = depth.point_cloud(disp, c, bgr)
    np.testing.assert_array_equal(want, bgr.reshape(-1, 3)[:, ::-1])
    for colour in (bgr.astype(np.uint16) * 257, (bgr.astype(np.uint16) * 257).astype(">u2"),
                   bgr / 255.0, (bgr / 255.0).astype(np.float32)):
        _, rgb = depth.point_cloud(disp, c, colour)
        np.testing.assert_array_equal(rgb, want, err_msg=str(colour.dtype))
    _, rgb = depth.point_cloud(disp, c, bgr.astype(np.uint16) * 256)  # 8-bit data shifted: within 1
    assert np.abs(rgb.astype(int) - want).max() <= 1 and rgb.max() > 0
    _, gray = depth.point_cloud(disp, c, bgr[:, :, 0] / 255.0)
    np.testing.assert_array_equal(gray, np.repeat(bgr[:, :, 0].reshape(-1, 1), 3, 1))
    _, clipped = depth.point_cloud(disp, c, np.full((3, 4), 1.5))
    assert (clipped == 255).all()
    for bad, words in ((bgr.astype(np.int32), "dtype int32"), (np.full((3, 4), np.nan), "finite"),
                       (bgr[:, :, :2], "shape")):
        with pytest.raises(InputError, match=words):
            depth.point_cloud(disp, c, bad)


def test_write_ply_scales_float_colours(tmp_path):
    pts = np.zeros((3, 3), np.float32)
    depth.write_ply(tmp_path / "c.ply", pts, np.array([[0.0, 0.5, 1.0]] * 3))
    _, cols = depth.read_ply(tmp_path / "c.ply")
    np.testing.assert_array_equal(cols, [[0, 128, 255]] * 3)
    depth.write_ply(tmp_path / "d.ply", pts, np.full((3, 3), 65535, np.uint16))
    assert (depth.read_ply(tmp_path / "d.ply")[1] == 255).all()
    with pytest.raises(InputError, match="dtype int64"):
        depth.write_ply(tmp_path / "e.ply", pts, np.full((3, 3), 300))


def test_colorize_negative_disparities():
    """vmin defaults to min(0, the smallest finite value): a map from a range
    with a negative minimum gets one colour per disparity, not one colour for
    every negative value."""
    from mccnn_cl.visualize import disparity_range

    neg = np.tile(np.arange(-32, 0, dtype=np.float32), (4, 1))
    assert disparity_range(neg) == (-32.0, -1.0)
    assert disparity_range(np.array([[3.0, 40.0, np.nan]])) == (0.0, 40.0)  # from 0 as before
    assert disparity_range(np.array([[-5.0, 40.0]]), None) == (-5.0, 40.0)
    assert disparity_range(np.full((2, 2), np.nan)) == (0.0, 1.0)
    img = colorize(neg)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) == 32
    legend = colorize_with_legend(neg)  # the 32-px map centred on the legend's 160-px canvas
    np.testing.assert_array_equal(legend[:4, 64:96], img)
