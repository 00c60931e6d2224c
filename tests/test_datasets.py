"""Dataset readers on the real shared data (the shared_data fixture; see its README for the table checked here)."""

import shutil

import numpy as np
import pytest

from mccnn_cl.evaluation.datasets import (discover, find_pairs, load_kitti2012, load_kitti2015,
                               load_middlebury)
from mccnn_cl.errors import InputError
from mccnn_cl.io import write_pfm

# README.md of the shared data: scene -> (width, height, GT min, GT max, has mask)
MIDDLEBURY = {
    "Tsukuba": (384, 288, 5, 14, True),
    "Venus": (434, 383, 3, 19.75, True),
    "Cones": (450, 375, 5.5, 55, True),
    "Cloth3": (626, 555, 22.5, 83, False),
    "Reindeer": (671, 555, 5.5, 100.5, False),
    "Aloe": (1282, 1110, 43, 211, False),
    "Motorcycle": (741, 500, 7.2, 59.9, False),
}


#: The KITTI 2015 frames of the shared data: two official ones and eight "e" frames (ids unknown).
KITTI2015 = ["000000", "000001"] + [f"e{n:05d}" for n in (1, 2, 3, 4, 6, 7, 8, 10)]
#: The shared data's pairs with ground truth, in discovery order.
LABELED = (["kitti2012/000000", "kitti2012/000001"] + [f"kitti2015/{f}" for f in KITTI2015]
           + [f"middlebury/{s}" for s in sorted(MIDDLEBURY)])


@pytest.mark.full_data
def test_every_pair_loads(shared_data):
    pairs = find_pairs(shared_data, labeled=True)
    keys = [p.key for p in pairs]
    assert keys == LABELED
    for p in pairs:
        assert p.left.dtype == np.uint8 and p.right.shape == p.left.shape
        assert p.disp.dtype == np.float32 and p.disp.shape == p.shape
        assert p.valid_all.dtype == bool
        np.testing.assert_array_equal(np.isfinite(p.disp), p.valid_all)
        if p.valid_noc is not None:
            assert not (p.valid_noc & ~p.valid_all).any()
            assert 0.5 < p.valid_noc.sum() / p.valid_all.sum() <= 1
        lg, rg = p.gray()
        assert lg.shape == p.shape and lg.dtype == np.uint8 and lg.std() > 5


@pytest.mark.full_data
def test_middlebury_table(shared_data):
    for scene, (w, h, lo, hi, has_mask) in MIDDLEBURY.items():
        p = load_middlebury(shared_data / "middlebury" / scene)
        assert p.shape == (h, w) and p.kind == "middlebury" and p.name == scene
        assert p.ndisp % 16 == 0 and p.ndisp > hi
        assert np.nanmin(p.disp) == pytest.approx(lo, abs=0.05)
        assert np.nanmax(p.disp) == pytest.approx(hi, abs=0.05)
        assert (p.valid_noc is not None) == has_mask
        assert p.calib.endswith("calib.txt")


@pytest.mark.full_data
def test_kitti(shared_data):
    k12 = load_kitti2012(shared_data / "kitti2012", 0)  # dataset root with training/
    assert k12.shape == (370, 1226) and k12.left.ndim == 3 and k12.valid_noc is None
    assert 4 < np.nanmin(k12.disp) and np.nanmax(k12.disp) < 130
    k15 = load_kitti2015(shared_data / "kitti2015" / "training", "000000_10.png")
    assert k15.shape == (375, 1242) and k15.name == "000000"
    assert k15.valid_noc is not None and k15.valid_noc.sum() < k15.valid_all.sum()
    assert k15.calib.endswith("000000.txt")
    k15b = load_kitti2015(shared_data / "kitti2015" / "training", 1)
    assert k15b.valid_noc is None and k15b.valid_all.sum() > 50000
    # Ground truth is sparse (LiDAR) but spans the disparity range.
    assert np.nanmax(k15.disp) > 60


@pytest.mark.full_data
def test_layout_detection(shared_data):
    assert [r.key for r in discover(shared_data / "kitti2015")] == [f"kitti2015/{f}" for f in KITTI2015]
    assert [r.key for r in discover(shared_data / "kitti2012" / "training")] == \
        ["kitti2012/000000", "kitti2012/000001"]
    assert [r.key for r in discover(shared_data / "middlebury" / "Cones")] == ["middlebury/Cones"]
    assert len(discover(shared_data / "middlebury")) == 7
    assert len(discover(shared_data, dataset="kitti2015")) == len(KITTI2015) == 10
    assert [r.key for r in discover(shared_data, labeled=True)] == LABELED
    with pytest.raises(InputError, match="unknown dataset"):
        discover(shared_data, dataset="sintel")


@pytest.mark.full_data
def test_unlabeled_pairs(shared_data, tmp_path):
    """Pairs without ground truth (the shared data's unlabeled/: ETH3D two-view and MiddEval3
    quarter-size scenes) are discovered as such, keep their collection in the key (a scene may
    also be in a labelled collection), and load with images only."""
    refs = discover(shared_data, labeled=False)
    keys = [r.key for r in refs]
    assert len(keys) == len(set(keys)) == 39 and not set(keys) & set(LABELED)
    assert sum(k.startswith("middlebury/eth3d_two_view/") for k in keys) == 27
    assert sum(k.startswith("middlebury/middeval3_trainingQ/") for k in keys) == 12
    assert "middlebury/middeval3_trainingQ/Adirondack" in keys
    assert len(discover(shared_data)) == len(LABELED) + 39  # both, labelled ones first (sorted folders)
    pair = next(r for r in refs if r.name.endswith("/Adirondack")).load()
    assert pair.disp is None and pair.valid_all is None and pair.valid_noc is None and pair.ndisp is None
    lg, rg = pair.gray()
    assert lg.dtype == np.uint8 and lg.shape == rg.shape == pair.shape and lg.std() > 5
    # a scene folder of one's own without GT, and the same with GT added
    scene = tmp_path / "mine" / "room"
    scene.mkdir(parents=True)
    for n in ("im0.png", "im1.png"):
        (scene / n).write_bytes((shared_data / "middlebury" / "Tsukuba" / n).read_bytes())
    (ref,) = discover(tmp_path)
    assert (ref.key, ref.labeled) == ("middlebury/mine/room", False)
    (scene / "disp0GT.pfm").write_bytes((shared_data / "middlebury" / "Tsukuba" / "disp0GT.pfm").read_bytes())
    (ref,) = discover(tmp_path)
    assert (ref.key, ref.labeled) == ("middlebury/room", True) and ref.load().disp is not None
    assert discover(tmp_path, labeled=False) == []


def test_errors(tmp_path, shared_data):
    with pytest.raises(InputError, match="not found"):
        find_pairs(tmp_path / "nothing")
    with pytest.raises(InputError, match="no stereo pairs"):
        find_pairs(tmp_path)
    with pytest.raises(InputError, match="not a kitti2012"):
        load_kitti2012(tmp_path, 0)
    with pytest.raises(InputError, match="not found"):
        load_kitti2015(shared_data / "kitti2015", 7)
    # A scene with a missing right image, then with a GT of the wrong size, then a corrupt PFM.
    scene = tmp_path / "Scene"
    scene.mkdir()
    src = shared_data / "middlebury" / "Tsukuba"
    shutil.copy(src / "im0.png", scene / "im0.png")
    with pytest.raises(InputError, match="im1.png"):
        load_middlebury(scene)
    shutil.copy(src / "im1.png", scene / "im1.png")
    write_pfm(scene / "disp0GT.pfm", np.ones((10, 10), np.float32))
    with pytest.raises(InputError, match="sizes differ"):
        load_middlebury(scene)
    (scene / "disp0GT.pfm").write_bytes(b"Pf\n384 288\n-1.0\n" + bytes(100))
    with pytest.raises(InputError, match="truncated"):
        load_middlebury(scene)
    (scene / "disp0GT.pfm").unlink()
    p = load_middlebury(scene)  # no GT: a test scene
    assert p.disp is None and p.valid_all is None and p.ndisp is None
    (scene / "calib.txt").write_text("width=100\nheight=288\nndisp=32\n")
    with pytest.raises(InputError, match="says 100x288"):
        load_middlebury(scene)


def test_middeval3_resolution_folders_keep_distinct_keys(tmp_path, shared_data):
    # MiddEval3 ships each scene at three resolutions (trainingQ/H/F) and test scenes without GT.
    src = shared_data / "middlebury" / "Tsukuba"
    for res in ("trainingQ", "trainingH", "testQ"):
        scene = tmp_path / "MiddEval3" / res / "Tsukuba"
        scene.mkdir(parents=True)
        for f in ("im0.png", "im1.png", "calib.txt") + (("disp0GT.pfm",) if res.startswith("training") else ()):
            (scene / f).symlink_to(src / f)
    refs = discover(tmp_path / "MiddEval3")
    assert [r.key for r in refs] == ["middlebury/testQ/Tsukuba", "middlebury/trainingH/Tsukuba",
                                     "middlebury/trainingQ/Tsukuba"]
    pairs = find_pairs(tmp_path / "MiddEval3" / "trainingQ")
    assert [p.key for p in pairs] == ["middlebury/trainingQ/Tsukuba"] and pairs[0].disp is not None
    assert refs[0].load().disp is None
