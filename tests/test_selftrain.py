"""Self-training (train/selftrain.py) and ``mccnn-cl adapt``.

Pseudo-labels are checked against a direct numpy computation from the
StereoResult; the unconfident case must stop or skip loudly; ``adapt`` runs
end to end (subprocess, the real entry point) on a 160 x 96 crop of a
shared ETH3D pair (its images only, as an unlabeled pair) with D = 32 and 2 x 2 steps; its input errors are one
line each.  kitti-fst (4 conv 3x3) keeps every OpenCL run well under a second.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

from mccnn_cl import cli
from mccnn_cl.io import read_image, write_image
from mccnn_cl.pipeline import StereoMatcher
from mccnn_cl.train import selftrain
from mccnn_cl.train.crops import CropSampler
from mccnn_cl.weights import Weights, resolve

D = 32


@pytest.fixture(scope="module")
def fst():
    return resolve("kitti-fst")


@pytest.fixture(scope="module")
def art(shared_data):
    """A 160 x 96 crop of ETH3D electro_1s (gray content in 3 channels; its images only, used as an
    unlabeled pair; GT disparities < 16 on the whole image, so D = 32 covers them)."""
    root = shared_data / "eth3d/two_view_training/electro_1s"
    l, r = read_image(root / "im0.png"), read_image(root / "im1.png")
    return l[100:196, 60:220].copy(), r[100:196, 60:220].copy()


@pytest.fixture(scope="module")
def result(ctx, fst, art):
    m = StereoMatcher(weights=fst, max_disparity=D, device=ctx)
    from mccnn_cl.evaluation.datasets import to_gray_u8
    return m.compute(to_gray_u8(art[0]), to_gray_u8(art[1]), confidence=True)


@pytest.mark.full_data
def test_pseudo_labels_keep_exactly_the_confident_lr_correct_pixels(result):
    res = result
    assert res.confidence.std() > 0 and (res.labels != 0).any() and (res.labels == 0).any()
    t = float(np.median(res.confidence[res.labels == 0]))  # a threshold that bites
    disp, mask = selftrain.pseudo_labels(res, t)
    h, w = res.disparity.shape
    m = res.margin
    expect = np.zeros((h, w), bool)
    for y in range(m, h - m):
        for x in range(m, w - m):
            expect[y, x] = (res.labels[y, x] == 0 and res.confidence[y, x] >= np.float32(t)
                            and np.isfinite(res.disparity[y, x]))
    np.testing.assert_array_equal(mask, expect)
    assert 0 < mask.sum() < (res.labels[m:h - m, m:w - m] == 0).sum()  # some correct pixels dropped
    np.testing.assert_array_equal(disp[mask], res.disparity[mask])
    assert np.isnan(disp[~mask]).all()
    # threshold 0 keeps every left-right correct pixel of the cropped domain
    _, all_correct = selftrain.pseudo_labels(res, 0.0)
    inner = np.zeros_like(all_correct)
    inner[m:h - m, m:w - m] = (res.labels == 0)[m:h - m, m:w - m]
    np.testing.assert_array_equal(all_correct, inner)
    # the crop sampler sees exactly those pixels as ground truth
    p = selftrain.pseudo_pair("art", np.zeros((h, w), np.uint8) + 1, np.zeros((h, w), np.uint8), disp, mask)
    assert CropSampler([p], 9).counts() == {"pseudo/art": int(mask.sum())}


@pytest.mark.full_data
def test_pseudo_labels_need_confidence(result):
    from dataclasses import replace
    with pytest.raises(selftrain.InputError, match="confidence=True"):
        selftrain.pseudo_labels(replace(result, confidence=None), 0.1)


@pytest.mark.full_data
def test_unconfident_pairs_are_skipped_loudly_and_none_is_an_error(ctx, fst, art, monkeypatch):
    real = selftrain._matcher
    FLAT_D = D + 16

    class Flat:  # the real matcher, but at D = FLAT_D every pixel comes out unconfident
        def __init__(self, m):
            self.m = m

        def compute(self, left, right, confidence):
            res = self.m.compute(left, right, confidence=confidence)
            if self.m.max_disparity == FLAT_D:
                res.confidence = np.zeros_like(res.confidence)
            return res

        def release_buffers(self):
            self.m.release_buffers()

    monkeypatch.setattr(selftrain, "_matcher", lambda *a: Flat(real(*a)))
    good = selftrain.UnlabeledPair("good", art[0], art[1], D)
    flat = selftrain.UnlabeledPair("flat", art[0], art[1], FLAT_D)
    said = []
    pseudo, stats = selftrain.label_pairs(fst, [good, flat], 0.05, ctx=ctx, log=said.append)
    assert [p.name for p in pseudo] == ["good"]
    assert stats["flat"]["kept"] == 0 and stats["good"]["kept"] > 0.1
    assert any("flat" in s and "skipped" in s for s in said)
    with pytest.raises(selftrain.InputError, match="nothing to train on"):
        selftrain.label_pairs(fst, [flat], 0.05, ctx=ctx, log=said.append)


def _write_pair(d, art, n=1):
    for i in range(n):
        write_image(d / f"L_{i}.png", art[0])
        write_image(d / f"R_{i}.png", art[1])


@pytest.mark.full_data
def test_adapt_writes_adapted_weights_with_provenance(tmp_path, art, fst):
    _write_pair(tmp_path, art)
    out = tmp_path / "adapted.npz"
    p = subprocess.run([sys.executable, "-m", "mccnn_cl", "adapt", str(tmp_path / "L_*.png"),
                        str(tmp_path / "R_*.png"), "--weights", "kitti-fst", "-o", str(out), "--ndisp", str(D),
                        "--rounds", "2", "--steps", "2", "--threads", "2"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "round 2/2" in p.stdout and "kept" in p.stdout
    w = Weights.load(out)
    assert w.architecture == fst.architecture and w.conv_layers() == fst.conv_layers()
    diff = max(float(np.abs(a[0] - b[0]).max()) for a, b in zip(w.conv, fst.conv))
    assert diff > 0
    assert w.stereo == fst.stereo  # the source's stereo settings are kept
    t = w.meta["training"]
    assert t["source_weights"] == "kitti-fst" and t["rounds"] == 2 and t["steps_per_round"] == 2
    assert t["min_confidence"] == selftrain.DEFAULT_MIN_CONFIDENCE
    assert t["pairs"] == [[str(tmp_path / "L_0.png"), str(tmp_path / "R_0.png")]]
    assert len(t["per_round"]) == 2
    for rec in t["per_round"]:
        (kept,) = rec["kept_fraction"].values()
        assert 0 < kept < 1 and rec["examples"] > 0
    assert t["held_out"] == fst.meta["training"]["held_out"]
    json.dumps(t)  # JSON all the way down


@pytest.mark.full_data
def test_adapt_input_errors(tmp_path, art, capsys):
    _write_pair(tmp_path, art)
    (tmp_path / "R_1.png").write_bytes((tmp_path / "R_0.png").read_bytes())
    small = tmp_path / "small"
    small.mkdir()
    write_image(small / "L_0.png", art[0])
    write_image(small / "R_0.png", art[1][:, :150])
    wf = tmp_path / "exists.npz"
    wf.write_bytes(b"x")
    L, R = str(tmp_path / "L_*.png"), str(tmp_path / "R_0.png")
    base = ["--ndisp", str(D), "--steps", "1", "--rounds", "1"]
    cases = [
        ([str(tmp_path / "none_*.png"), R, "--weights", "kitti-fst", "-o", tmp_path / "o.npz"], "no left images match"),
        ([L, str(tmp_path / "R_*.png"), "--weights", "kitti-fst", "-o", tmp_path / "o.npz"], "1 left but 2 right"),
        ([str(small / "L_*.png"), str(small / "R_*.png"), "--weights", "kitti-fst", "-o", tmp_path / "o.npz"],
         "differ in size"),
        ([L, R, "--weights", "census", "-o", tmp_path / "o.npz"], "census has no network"),
        ([L, R, "--weights", tmp_path / "missing.npz", "-o", tmp_path / "o.npz"], "not found"),
        ([L, R, "--weights", "kitti-fst", "-o", tmp_path / "o.pfm"], ".npz"),
        ([L, R, "--weights", "kitti-fst", "-o", wf], "--force"),
        ([L, R, "--weights", "kitti-fst", "-o", tmp_path / "nodir/o.npz"], "does not exist"),
        ([L, R, "--weights", "kitti-fst", "-o", tmp_path / "o.npz", "--min-confidence", "1.5"], "[0, 1]"),
        ([L, R, "--weights", "kitti-fst", "-o", tmp_path / "o.npz", "--rounds", "0"], "--rounds must be >= 1"),
        ([L, R, "--weights", "kitti-fst", "-o", tmp_path / "o.npz", "--ndisp", "200"],
         "not smaller than the image width"),
    ]
    for args, word in cases:
        rc = cli.main(["adapt", *map(str, args[:2]), *base, *map(str, args[2:])])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and err[0].startswith("mccnn-cl: error:") and word in err[0], (args, err)
    assert not (tmp_path / "o.npz").exists()


@pytest.mark.full_data
def test_self_train_control_and_mixing(ctx, fst, art, tmp_path, shared_data):
    """No unlabeled pairs: fine-tunes on labeled pairs only (the A/B's control, same schedule);
    with share=0.5 the pseudo-labels are thinned to as many pixels as the labeled pairs hold."""
    from mccnn_cl.evaluation.datasets import load_middlebury
    ts = load_middlebury(shared_data / "middlebury/Tsukuba")
    cfg = selftrain.default_config(fst, crops_per_step=1)
    w, prov = selftrain.self_train(fst, [], cfg, 1, 1, 0.1, labeled=[ts], out_dir=tmp_path / "a")
    assert prov["per_round"][0]["labeled_pixels"] == int(ts.valid_all.sum()) and "kept_fraction" not in prov["per_round"][0]
    assert "middlebury/Tsukuba" in prov["trained_on"]
    small = selftrain.UnlabeledPair("art", art[0], art[1], D)
    rows = (np.arange(ts.shape[0]) >= 40) & (np.arange(ts.shape[0]) < 48)
    labeled_px = int(ts.valid_all[rows].sum())
    ts40 = selftrain.pseudo_pair("ts40", ts.left, ts.right, ts.disp, ts.valid_all & rows[:, None])
    w, prov = selftrain.self_train(fst, [small], cfg, 1, 1, 0.0, labeled=[ts40], share=0.5,
                                   out_dir=tmp_path / "b", ctx=ctx, log=lambda *a: None)
    rec = prov["per_round"][0]
    assert rec["labeled_pixels"] == labeled_px
    assert rec["thinned_to"] < 1 and abs(rec["pseudo_pixels"] - labeled_px) < 0.15 * labeled_px
    with pytest.raises(selftrain.InputError, match="share"):
        selftrain.self_train(fst, [small], cfg, 1, 1, 0.1, labeled=[ts], share=1.0, out_dir=tmp_path / "c")


# -- provenance of a self-trained network (no OpenCL: labeled pairs only, the A/B's control path) ------

def _converted_start(trained_on):
    """A small fst network with the metadata a converted published network carries (an older
    converter wrote ``trained_on`` as a list of keys)."""
    from mccnn_cl.importers import APACHE2

    w = Weights.random(conv_layers=[[8, 3], [8, 3]], architecture="mccnn-fst", seed=3)
    w.meta.update(licence=APACHE2, source={"file": "mc_cnn_fast_mb_weights.pt", "sha256": "0" * 64},
                  training={"by": "CNES (PyPI mccnn)", "data": "Middlebury", "trained_on": trained_on})
    return w


@pytest.fixture(scope="module")
def tsukuba(shared_data):
    from mccnn_cl.evaluation.datasets import load_middlebury
    return load_middlebury(shared_data / "middlebury/Tsukuba")


def test_self_train_from_a_converted_start_keeps_its_weights_and_lineage(tsukuba, tmp_path):
    """A start whose trained_on is a list (converted files of older versions) or a dict (the
    importer's form now): the run ends with weights and its provenance counts the start's pairs
    (the list raised ValueError after all training)."""
    from mccnn_cl.evaluation.scoring import training_status

    for form in (["kitti2012/000000", "kitti2012/000001"],
                 {"kitti2012/000000": {"by": "J. Z."}, "kitti2012/000001": {"by": "J. Z."}}):
        start = _converted_start(form)
        cfg = selftrain.default_config(start, crops_per_step=1)
        w, prov = selftrain.self_train(start, [], cfg, 1, 1, 0.5, labeled=[tsukuba], out_dir=tmp_path / "r",
                                       log=lambda *a: None)
        assert set(prov["trained_on"]) == {"kitti2012/000000", "kitti2012/000001", "middlebury/Tsukuba"}
        assert training_status(w.meta, "kitti2012/000001", "000001") == "trained"
        assert w.conv_layers() == start.conv_layers() and w.meta["training"] is prov
        json.dumps(prov)


def test_self_train_records_the_schedule_that_ran_and_the_start(tsukuba, tmp_path):
    """config is what each round ran (1 epoch x steps, constant lr, seed + round), not the default
    recipe's 16 x 500; source_training keeps who trained the start on what, its licence and file."""
    from mccnn_cl.importers import APACHE2

    start = _converted_start({"middlebury/Venus": 5})
    cfg = selftrain.default_config(start, crops_per_step=1, seed=4)
    assert cfg.epochs != 1 and cfg.steps_per_epoch != 2  # the recipe's schedule is not the one run
    _, prov = selftrain.self_train(start, [], cfg, 2, 2, 0.5, labeled=[tsukuba], out_dir=tmp_path / "r",
                                   source_name="cnes.npz", log=lambda *a: None)
    c, st = prov["config"], prov["source_training"]
    assert (c["epochs"], c["steps_per_epoch"], c["lr_steps"]) == (1, 2, [])
    assert st.get("by") == "CNES (PyPI mccnn)" and st.get("data") == "Middlebury" and st["weights"] == "cnes.npz"
    assert c["seeds"] == [4, 5] and c["seed"] == 4
    assert prov["total_steps"] == 4 and "2 round(s)" in prov["schedule"] and len(prov["per_round"]) == 2
    assert st["licence"] == APACHE2 and st["source"]["file"] == "mc_cnn_fast_mb_weights.pt"


def test_self_train_keeps_the_weights_when_the_provenance_fails(tsukuba, tmp_path, monkeypatch):
    def broken(*a, **k):
        raise KeyError("something in the start's metadata")

    monkeypatch.setattr(selftrain, "provenance", broken)
    start = _converted_start({})
    said = []
    w, prov = selftrain.self_train(start, [], selftrain.default_config(start, crops_per_step=1), 1, 1, 0.5,
                                   labeled=[tsukuba], out_dir=tmp_path / "r", log=said.append)
    assert "KeyError" in prov["provenance_error"] and prov["source_training"]["licence"] == start.meta["licence"]
    from mccnn_cl.train.ship import licence_for
    assert licence_for({"training": prov}).endswith(start.meta["licence"])  # the start's licence is not lost
    assert any("warning" in s and "provenance" in s for s in said)
    w.save(tmp_path / "kept.npz")
    assert Weights.load(tmp_path / "kept.npz").meta["training"]["rounds"] == 1


def test_adapt_refuses_an_output_folder_before_any_work(tmp_path, capsys):
    """-o NAME.npz that is a folder: one error line before reading images or training, --force or not
    (it failed only when writing, after all training)."""
    (tmp_path / "out.npz").mkdir()
    rc = cli.main(["adapt", str(tmp_path / "none_L*.png"), str(tmp_path / "none_R*.png"), "--weights",
                   "kitti-fst", "-o", str(tmp_path / "out.npz"), "--force", "--ndisp", "32"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "is a folder" in err[0], err
