"""Readers and writers of mccnn_cl.io: round trips, the PFM byte order and row order, errors."""

import cv2
import numpy as np
import pytest

from mccnn_cl.atomic import PREFIX
from mccnn_cl.errors import InputError
from mccnn_cl.io import (read_image, read_kitti_disparity, read_pfm, write_image,
                         write_kitti_disparity, write_pfm)


def test_pfm_round_trip_gray_and_colour(tmp_path):
    rng = np.random.default_rng(0)
    a = rng.normal(0, 50, (37, 53)).astype(np.float32)
    a[3, 5] = np.inf
    write_pfm(tmp_path / "a.pfm", a)
    np.testing.assert_array_equal(read_pfm(tmp_path / "a.pfm"), a)
    c = rng.normal(0, 1, (5, 7, 3)).astype(np.float32)
    write_pfm(tmp_path / "c.pfm", c)
    back = read_pfm(tmp_path / "c.pfm")
    assert back.shape == (5, 7, 3) and back.dtype == np.float32
    np.testing.assert_array_equal(back, c)
    assert not list(tmp_path.glob(PREFIX + "*")), "temporary files left behind"


def test_pfm_rows_bottom_to_top_and_big_endian(tmp_path):
    # Hand-made big-endian file (positive scale): first stored row is the image's last row.
    data = np.array([[1, 2, 3], [4, 5, 6]], np.float32)
    p = tmp_path / "be.pfm"
    p.write_bytes(b"Pf\n3 2\n1.0\n" + data[::-1].astype(">f4").tobytes())
    np.testing.assert_array_equal(read_pfm(p), data)
    p2 = tmp_path / "le.pfm"
    p2.write_bytes(b"Pf\n3 2\n-1.0\n" + data[::-1].astype("<f4").tobytes())
    np.testing.assert_array_equal(read_pfm(p2), data)


@pytest.mark.full_data
def test_pfm_real_middlebury_has_inf_unknowns(shared_data):
    gt = read_pfm(shared_data / "middlebury" / "Cones" / "disp0GT.pfm")
    assert gt.shape == (375, 450) and gt.dtype == np.float32
    fin = gt[np.isfinite(gt)]
    assert np.isinf(gt).any() and fin.min() == 5.5 and fin.max() == 55.0


def test_pfm_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_pfm(tmp_path / "missing.pfm")
    (tmp_path / "bad.pfm").write_bytes(b"P6\n3 2\n255\n" + bytes(18))
    with pytest.raises(InputError, match="not a PFM"):
        read_pfm(tmp_path / "bad.pfm")
    (tmp_path / "short.pfm").write_bytes(b"Pf\n3 2\n-1.0\n" + bytes(10))
    with pytest.raises(InputError, match="truncated"):
        read_pfm(tmp_path / "short.pfm")
    with pytest.raises(InputError):
        write_pfm(tmp_path / "x.pfm", np.zeros((2, 3, 4), np.float32))


def test_kitti_png_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    d = np.round(rng.uniform(0.5, 200, (37, 53)) * 256) / 256
    d[0, :5] = 0
    d[1, 1] = np.nan
    d[2, 2] = np.inf  # invalid; a negative value is refused (tests/test_robustness.py)
    write_kitti_disparity(tmp_path / "d.png", d)
    back, valid = read_kitti_disparity(tmp_path / "d.png")
    assert back.dtype == np.float32 and valid.dtype == bool
    expect_valid = np.isfinite(d) & (d > 0)
    np.testing.assert_array_equal(valid, expect_valid)
    np.testing.assert_array_equal(back[valid], d[expect_valid].astype(np.float32))
    assert (back[~valid] == 0).all()


@pytest.mark.full_data
def test_kitti_png_real(shared_data):
    disp, valid = read_kitti_disparity(shared_data / "kitti2015/training/disp_occ_0/000000_10.png")
    assert disp.shape == (375, 1242) and 0 < valid.mean() < 0.5
    assert 4 < disp[valid].min() and disp[valid].max() < 130


def test_kitti_png_errors(tmp_path, shared_data):
    with pytest.raises(InputError, match="not found"):
        read_kitti_disparity(tmp_path / "none.png")
    # An 8-bit colour image is not a disparity map.
    with pytest.raises(InputError, match="16-bit"):
        read_kitti_disparity(shared_data / "kitti2015/training/image_2/000000_10.png")
    (tmp_path / "junk.png").write_bytes(b"not a png at all")
    with pytest.raises(InputError, match="unreadable"):
        read_kitti_disparity(tmp_path / "junk.png")


def test_read_image(tmp_path, shared_data):
    img = read_image(shared_data / "middlebury/Tsukuba/im0.png")
    assert img.shape == (288, 384, 3) and img.dtype == np.uint8
    g = read_image(shared_data / "middlebury/Tsukuba/im0.png", gray=True)
    assert g.shape == (288, 384) and g.std() > 10
    write_image(tmp_path / "g.png", g)
    np.testing.assert_array_equal(read_image(tmp_path / "g.png"), g)
    with pytest.raises(InputError, match="not found"):
        read_image(tmp_path / "nope.png")
    with pytest.raises(InputError, match="not a file"):
        read_image(tmp_path)
    (tmp_path / "junk.png").write_bytes(b"garbage")
    with pytest.raises(InputError, match="unreadable"):
        read_image(tmp_path / "junk.png")


@pytest.mark.parametrize("params", [[], [cv2.IMWRITE_JPEG_PROGRESSIVE, 1], [cv2.IMWRITE_JPEG_RST_INTERVAL, 4]],
                         ids=["baseline", "progressive", "restarts"])
def test_truncated_jpeg_is_refused(tmp_path, shared_data, params):
    """cv2 decodes a JPEG cut short (grey below the cut, a libjpeg line on stderr): refuse it.
    Whole files, with data after their end (a motion photo's video), still read."""
    from mccnn_cl.io import jpeg_complete
    img = read_image(shared_data / "middlebury/Tsukuba/im0.png")
    ok, buf = cv2.imencode(".jpg", img, params)
    data = buf.tobytes()
    (tmp_path / "whole.jpg").write_bytes(data + b"appended\xff\xda\x00\xff")
    assert read_image(tmp_path / "whole.jpg").shape == img.shape
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) * 2 // 3])
    assert cv2.imread(str(tmp_path / "cut.jpg")) is not None  # what cv2 alone would have matched
    with pytest.raises(InputError, match="truncated"):
        read_image(tmp_path / "cut.jpg")
    assert not any(jpeg_complete(data[:k]) for k in range(2, len(data), 61))


def test_read_image_reads_the_file_once(tmp_path, shared_data, monkeypatch):
    """read_image opens its file once, for every kind of image (a JPEG too, whose end it
    checks): the bytes checked for truncation are the bytes decoded.  (Before, cv2.imread
    opened the file and then read_image opened it again for the check.)  The images are
    those cv2.imread gives, in both modes."""
    import builtins
    import os

    src = read_image(shared_data / "middlebury/Tsukuba/im0.png")
    files = []
    for ext, params in ((".png", []), (".jpg", []), (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]), (".bmp", [])):
        ok, buf = cv2.imencode(ext, src, params)
        assert ok
        files.append(tmp_path / f"im{len(files)}{ext}")
        files[-1].write_bytes(buf.tobytes())
    files.append(tmp_path / "bgra.png")
    cv2.imwrite(str(files[-1]), np.dstack([src, np.full(src.shape[:2], 9, np.uint8)]))
    expected = {(f, g): cv2.imread(str(f), cv2.IMREAD_GRAYSCALE if g else cv2.IMREAD_UNCHANGED)
                for f in files for g in (False, True)}

    opened = []
    real_open, real_imread = builtins.open, cv2.imread

    def counting_open(file, *a, **k):
        opened.append(os.fspath(file) if isinstance(file, (str, bytes, os.PathLike)) else file)
        return real_open(file, *a, **k)

    def counting_imread(file, *a, **k):  # cv2 opens the file itself
        opened.append(os.fspath(file))
        return real_imread(file, *a, **k)

    monkeypatch.setattr(builtins, "open", counting_open)
    monkeypatch.setattr(cv2, "imread", counting_imread)
    for (f, g), want in expected.items():
        opened.clear()
        got = read_image(f, gray=g)
        assert opened.count(str(f)) == 1, (f.name, g, opened)
        if want.ndim == 3 and want.shape[2] == 4:
            want = cv2.cvtColor(want, cv2.COLOR_BGRA2BGR)
        np.testing.assert_array_equal(got, want)
    monkeypatch.undo()
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(InputError, match="unreadable"):
        read_image(tmp_path / "empty.png")
