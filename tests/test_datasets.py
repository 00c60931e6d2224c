"""Dataset readers on the real shared data (the shared_data fixture; see its README for the table checked here)."""

import shutil

import numpy as np
import pytest

from mccnn_cl.evaluation.datasets import (ETH3D_NDISP, dataset_of, discover, find_pairs, load_eth3d, load_kitti2012,
                                         load_kitti2015, load_middlebury, scene_family)
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
#: The 2005/2006 half-size Middlebury scenes added with left-right-check masks.
MIDDLEBURY_0506 = ["Baby1", "Baby2", "Baby3", "Books", "Bowling1", "Bowling2", "Cloth1", "Cloth2", "Cloth4",
                   "Flowerpots", "Laundry", "Midd1", "Midd2", "Moebius", "Monopoly", "Rocks1", "Rocks2"]
#: MiddEval3 quarter-size training scenes (GT merged into the official layout).
MIDDEVAL3 = ["Adirondack", "Jadeplant", "Piano", "PianoL", "Pipes", "Playroom", "Shelves", "Vintage"]
#: ETH3D two-view low-res training scenes.
ETH3D = [f"{place}_{n}" for place, ns in (("delivery_area", ("1l", "1s", "2l", "2s")),
                                          ("electro", ("1l", "1s", "2l", "2s")), ("facade", ("1s",)),
                                          ("forest", ("1s",)), ("playground", ("1l", "1s", "2l", "2s")),
                                          ("terrace", ("1s", "2s")), ("terrains", ("1l", "1s"))) for n in ns]
#: The shared data's pairs with ground truth, in discovery order (sorted folders).
LABELED = ([f"eth3d/{s}" for s in ETH3D] + ["kitti2012/000000", "kitti2012/000001"]
           + [f"kitti2015/{f}" for f in KITTI2015] + [f"middlebury/trainingQ/{s}" for s in MIDDEVAL3]
           + [f"middlebury/{s}" for s in sorted(list(MIDDLEBURY) + MIDDLEBURY_0506)])


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
    assert len(discover(shared_data / "middlebury")) == len(MIDDLEBURY) + len(MIDDLEBURY_0506) == 24
    assert len(discover(shared_data, dataset="kitti2015")) == len(KITTI2015) == 10
    assert [r.key for r in discover(shared_data, labeled=True)] == LABELED
    with pytest.raises(InputError, match="unknown dataset"):
        discover(shared_data, dataset="sintel")


@pytest.mark.full_data
def test_every_family_is_found(shared_data):
    """All 62 labelled pairs of the shared data, each with its dataset and scene family."""
    refs = discover(shared_data)
    assert len(refs) == len(LABELED) == 62 and all(r.labeled for r in refs)
    count = {d: sum(r.dataset == d for r in refs) for d in ("kitti", "middlebury", "middeval3", "eth3d")}
    assert count == {"kitti": 12, "middlebury": 24, "middeval3": 8, "eth3d": 18}
    fam = {r.key: r.family for r in refs}
    assert {k for k, f in fam.items() if f == "middlebury/Cloth"} == {f"middlebury/Cloth{i}" for i in range(1, 5)}
    assert {k for k, f in fam.items() if f == "middlebury/Baby"} == {f"middlebury/Baby{i}" for i in range(1, 4)}
    assert {k for k, f in fam.items() if f == "middeval3/Piano"} == {"middlebury/trainingQ/Piano",
                                                                      "middlebury/trainingQ/PianoL"}
    assert {k for k, f in fam.items() if f == "eth3d/delivery_area"} == {
        f"eth3d/delivery_area_{n}" for n in ("1l", "1s", "2l", "2s")}
    assert fam["kitti2015/000000"] == "kitti2015/000000" and fam["middlebury/Cones"] == "middlebury/Cones"
    assert len(set(fam.values())) == 42  # 12 KITTI frames, 16 Middlebury, 7 MiddEval3, 7 ETH3D families
    assert dataset_of("middlebury/trainingH/Motorcycle") == "middeval3"
    assert scene_family("middlebury/trainingF/MotorcycleE") == "middeval3/Motorcycle"
    assert scene_family("middlebury/Midd2") == "middlebury/Midd"
    # the same scene under another rectification or exposure (not in the shared data)
    assert scene_family("middlebury/trainingQ/PlaytableP") == scene_family("middlebury/trainingQ/Playtable")
    assert scene_family("middlebury/testH/Classroom2E") == "middeval3/Classroom2"
    assert scene_family("middlebury/trainingQ/ArtL") == "middeval3/Art"
    assert scene_family("middlebury/Adirondack-perfect") == scene_family("middlebury/Adirondack-imperfect") \
        == "middlebury/Adirondack"


@pytest.mark.full_data
def test_eth3d(shared_data):
    """ETH3D two-view: images beside the GT archive's folder; the calib's ndisp (the image width) is
    replaced by ETH3D_NDISP, which bounds every scene's GT."""
    root = shared_data / "eth3d" / "two_view_training"
    assert [r.key for r in discover(root)] == [f"eth3d/{s}" for s in ETH3D]
    assert [r.key for r in discover(shared_data, dataset="eth3d")] == [f"eth3d/{s}" for s in ETH3D]
    for name in ETH3D:
        p = load_eth3d(root / name)
        assert p.kind == "eth3d" and p.key == f"eth3d/{name}" and p.dataset == "eth3d"
        h, w = p.shape
        assert (700 <= w <= 720 if name.endswith("s") else 925 <= w <= 945) and 425 <= h <= 491
        assert p.calib_ndisp == w and p.ndisp == ETH3D_NDISP
        assert p.left.shape == p.right.shape and p.left.std() > 5
        np.testing.assert_array_equal(np.isfinite(p.disp), p.valid_all)
        assert 0 < np.nanmin(p.disp) and p.max_gt() < ETH3D_NDISP
        assert not (p.valid_noc & ~p.valid_all).any() and 0.5 < p.valid_noc.sum() / p.valid_all.sum() < 1
    assert load_eth3d(root / "forest_1s").max_gt() == pytest.approx(61.3, abs=0.05)


@pytest.mark.full_data
def test_pairs_without_ground_truth(shared_data, tmp_path):
    """ETH3D's test split (no GT folder), a Middlebury scene without GT: discovered as unlabeled, loaded
    with images only, keyed apart from labelled collections."""
    src = shared_data / "eth3d" / "two_view_training" / "electro_1s"
    scene = tmp_path / "eth3d" / "two_view_test" / "lakeside_1l"
    scene.mkdir(parents=True)
    for n in ("im0.png", "im1.png", "calib.txt"):
        shutil.copy(src / n, scene / n)
    mine = tmp_path / "mine" / "room"
    mine.mkdir(parents=True)
    for n in ("im0.png", "im1.png"):
        (mine / n).write_bytes((shared_data / "middlebury" / "Tsukuba" / n).read_bytes())
    refs = discover(tmp_path)
    assert [(r.key, r.labeled) for r in refs] == [("eth3d/lakeside_1l", False), ("middlebury/mine/room", False)]
    assert discover(tmp_path, labeled=True) == []
    p = refs[0].load()
    assert p.disp is None and p.valid_all is None and p.valid_noc is None
    assert p.ndisp == ETH3D_NDISP and p.calib_ndisp == p.shape[1]
    # the training split without its GT folder beside it: images only as well
    train = tmp_path / "t" / "two_view_training" / "electro_1s"
    shutil.copytree(scene, train)
    (ref,) = discover(tmp_path / "t")
    assert (ref.key, ref.labeled) == ("eth3d/electro_1s", False) and ref.load().disp is None
    # ... and with a GT of the wrong size
    gt = tmp_path / "t" / "two_view_training_gt" / "electro_1s"
    gt.mkdir(parents=True)
    write_pfm(gt / "disp0GT.pfm", np.ones((10, 10), np.float32))
    (ref,) = discover(tmp_path / "t")
    assert ref.labeled
    with pytest.raises(InputError, match="sizes differ"):
        ref.load()
    (mine / "disp0GT.pfm").write_bytes((shared_data / "middlebury" / "Tsukuba" / "disp0GT.pfm").read_bytes())
    assert [r.key for r in discover(tmp_path / "mine")] == ["middlebury/room"]


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
