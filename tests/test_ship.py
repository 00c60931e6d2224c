"""train/ship.py: a run's weights become a shipped file with name, licence and stereo settings."""

import pytest

from mccnn_cl.errors import InputError
from mccnn_cl.pipeline import Hyperparameters
from mccnn_cl.settings import authors_settings
from mccnn_cl.weights import Weights, shipped_models

try:  # mccnn_cl.train needs torch (the train extra); the set-up installs it: missing is an error, not a skip
    import torch  # noqa: F401
except ImportError as exc:
    raise ImportError(f"tests/test_ship.py needs torch, which the set-up installs (bash scripts/setup.sh: torch and "
                      f"the train extra); import failed: {exc}") from exc
from mccnn_cl.train import ship  # noqa: E402


def test_ship_adds_metadata_and_keeps_weights(tmp_path):
    src = Weights.load(shipped_models()["kitti-fst"])
    out = tmp_path / "x.npz"
    ship.main([shipped_models()["kitti-fst"], "-o", str(out), "--name", "x", "--settings", "mccnn-acrt/kitti2015",
               "--description", "a test", "--settings-note", "chosen on training frames"])
    w = Weights.load(out)
    assert w.meta["name"] == "x" and w.meta["description"] == "a test"
    assert w.stereo == authors_settings("mccnn-acrt", "kitti2015")
    assert "kitti2015" in w.meta["stereo_source"] and "training frames" in w.meta["stereo_source"]
    assert w.meta["training"] == src.meta["training"]
    for (a, b), (c, d) in zip(w.conv, src.conv):
        assert (a == c).all() and (b == d).all()
    Hyperparameters(**w.stereo)  # valid names and values


def test_licence_names_every_dataset_trained_on(tmp_path):
    """The licence line follows the training pairs, the start's included (kitti-paper's lineage
    holds 5 Middlebury scenes; the line said KITTI only)."""
    src = Weights.load(shipped_models()["kitti-fst"])
    assert ship.licence_for(src.meta) == "BSD-3-Clause (mccnn_cl); trained on KITTI (CC BY-NC-SA 3.0) images"
    src.meta["training"]["trained_on"] = {"kitti2015/000001": 5, "eth3d/electro_1s": 3}
    path = tmp_path / "mixed.npz"
    src.save(path)
    out = ship.ship(path, tmp_path / "m.npz", "m", "paper", "d")
    assert out.meta["licence"].endswith("KITTI (CC BY-NC-SA 3.0) and ETH3D (CC BY-NC-SA 4.0) images")
    assert ship.ship(path, tmp_path / "n.npz", "n", "paper", "d", licence="mine").meta["licence"] == "mine"
    for name, file in shipped_models().items():  # the shipped files carry their own datasets' line
        w = Weights.load(file)
        assert w.meta["licence"] == ship.licence_for(w.meta), name


def test_ship_paper_settings_are_the_defaults(tmp_path):
    out = tmp_path / "p.npz"
    ship.ship(shipped_models()["kitti-fst"], out, "p", "paper", "d")
    assert Weights.load(out).stereo == {}


def test_ship_rejects_unknown_settings_and_untrained_files(tmp_path, capsys):
    assert ship.main([shipped_models()["kitti-fst"], "-o", str(tmp_path / "y.npz"), "--name", "y",
                      "--settings", "mccnn-acrt/nowhere", "--description", "d"]) == 2
    assert "unknown settings" in capsys.readouterr().err
    w = Weights.load(shipped_models()["kitti-fst"])
    del w.meta["training"]
    bare = tmp_path / "bare.npz"
    w.save(bare)
    with pytest.raises(InputError, match="training"):
        ship.ship(bare, tmp_path / "z.npz", "z", "paper", "d")


def test_lineage_of_a_fine_tuned_network_counts_the_start_as_trained(tmp_path):
    """A run started from other weights (--init) learnt from their pairs too: evaluate must not
    call those pairs held out (record_init, used by the train CLI and by ship --init)."""
    from mccnn_cl.evaluation.scoring import training_status

    start = Weights.load(shipped_models()["kitti-fst"])
    run = Weights.load(shipped_models()["kitti-fst"])
    run.meta["training"] = {"trained_on": {"middlebury/Venus": 10}, "held_out": ["middlebury/Cones"]}
    src = tmp_path / "run.npz"
    run.save(src)
    assert training_status(run.meta, "kitti2015/e00001", "e00001") == "held out"
    out = tmp_path / "shipped.npz"
    ship.ship(src, out, "n", "paper", "d", init=shipped_models()["kitti-fst"])
    meta = Weights.load(out).meta
    assert meta["training"]["init"]["trained_on"] == start.meta["training"]["trained_on"]
    assert meta["training"]["trained_on_this_run"] == {"middlebury/Venus": 10}
    assert training_status(meta, "kitti2015/e00001", "e00001") == "trained"   # the start's pair
    assert training_status(meta, "middlebury/Venus", "Venus") == "trained"    # this run's
    assert training_status(meta, "middlebury/Cones", "Cones") == "held out"
    # a pair this run held out but its start trained on is not held out of the network
    start.meta["training"]["held_out"] = ["kitti2015/e00001", "middlebury/Cones"]
    assert training_status(start.meta, "kitti2015/e00001", "e00001") == "trained"
    assert training_status(start.meta, "middlebury/Cones", "Cones") == "held out"
    with pytest.raises(InputError, match="already"):
        ship.ship(out, tmp_path / "again.npz", "n", "paper", "d", init=shipped_models()["kitti-fst"])


def test_ship_set_changes_single_settings_and_says_so(tmp_path, capsys):
    out = tmp_path / "s.npz"
    assert ship.main([shipped_models()["kitti-fst"], "-o", str(out), "--name", "s", "--settings", "mccnn-fst/mb",
                      "--set", "cbca_iterations_after=4", "--set", "cbca_eta=5", "--description", "d"]) == 0
    w = Weights.load(out)
    assert w.stereo == dict(authors_settings("mccnn-fst", "mb"), cbca_iterations_after=4, cbca_eta=5)
    assert "changed here: cbca_iterations_after=4, cbca_eta=5" in w.meta["stereo_source"]
    assert "unchanged" not in w.meta["stereo_source"]
    for bad, says in ((["--set", "no_such_knob=1"], "unknown hyperparameter"), (["--set", "cbca_eta"], "NAME=VALUE"),
                      (["--set", "cbca_iterations_after=-3"], "cbca_iterations_after")):
        assert ship.main([shipped_models()["kitti-fst"], "-o", str(tmp_path / "t.npz"), "--name", "t",
                          "--settings", "mccnn-fst/mb", "--description", "d"] + bad) == 2
        assert says in capsys.readouterr().err
    assert not (tmp_path / "t.npz").exists()


# -- starts that are converted networks: their pairs, licence and source -----------------------------

def _start(licence, trained_on=None, tmp_path=None):
    """A small fst network with a converted file's metadata (``trained_on`` a list: older converters)."""
    w = Weights.random(conv_layers=[[8, 3], [8, 3]], architecture="mccnn-fst", seed=1)
    w.meta.update(licence=licence, source={"file": "mc_cnn_fast_mb_weights.pt", "sha256": "0" * 64},
                  training={"by": "CNES (PyPI mccnn)", "data": "Middlebury"})
    if trained_on is not None:
        w.meta["training"]["trained_on"] = trained_on
    if tmp_path is not None:
        w.save(tmp_path / "start.npz")
    return w


def test_record_init_takes_listed_pairs_and_keeps_licence_and_source():
    from mccnn_cl.importers import APACHE2
    from mccnn_cl.train.train import record_init

    start = _start(APACHE2, ["kitti2012/000000", "kitti2012/000001"])
    prov = record_init({"trained_on": {"middlebury/Venus": 10}}, start, "cnes.npz")
    assert set(prov["trained_on"]) == {"kitti2012/000000", "kitti2012/000001", "middlebury/Venus"}
    assert prov["trained_on_this_run"] == {"middlebury/Venus": 10}
    assert prov["init"]["licence"] == APACHE2 and prov["init"]["source"]["file"] == "mc_cnn_fast_mb_weights.pt"
    assert prov["init"]["by"] == "CNES (PyPI mccnn)"
    line = ship.licence_for({"training": prov})
    assert line.startswith("BSD-3-Clause (mccnn_cl); trained on KITTI (CC BY-NC-SA 3.0) and Middlebury")
    assert line.endswith(f"fine-tuned from mc_cnn_fast_mb_weights.pt, under its licence: {APACHE2}")


def test_shipping_a_network_fine_tuned_from_cnes_keeps_apache(tmp_path):
    """ship --init a converted CNES file: the shipped licence names CNES's Apache-2.0 (it was dropped)."""
    from mccnn_cl.importers import APACHE2

    _start(APACHE2, tmp_path=tmp_path)
    run = Weights.random(conv_layers=[[8, 3], [8, 3]], architecture="mccnn-fst", seed=2)
    run.meta["training"] = {"trained_on": {"middlebury/Venus": 10}}
    run.save(tmp_path / "run.npz")
    w = ship.ship(tmp_path / "run.npz", tmp_path / "s.npz", "s", "paper", "d", init=tmp_path / "start.npz")
    assert APACHE2 in w.meta["licence"] and "Middlebury" in w.meta["licence"]
    assert Weights.load(tmp_path / "s.npz").meta["training"]["init"]["licence"] == APACHE2
    # an adapted network (selftrain's provenance) carries its start's licence the same way
    from mccnn_cl.train import selftrain

    prov = selftrain.provenance(Weights.load(tmp_path / "start.npz"), "start.npz", [], [],
                                selftrain.default_config(run), 1, 1, 0.5, None, "network", [], {"cam_0": 900}, 1.0)
    line = ship.licence_for({"training": prov})
    assert "the user's own images" in line and line.endswith(f"under its licence: {APACHE2}")
    # and a network fine-tuned from that adapted one still does
    adapted = Weights.load(tmp_path / "start.npz")
    adapted.meta["training"] = prov
    adapted.save(tmp_path / "adapted.npz")
    w2 = ship.ship(tmp_path / "run.npz", tmp_path / "s2.npz", "s2", "paper", "d", init=tmp_path / "adapted.npz")
    assert w2.meta["licence"].count(APACHE2) == 1


def test_a_start_of_unknown_licence_needs_one_given(tmp_path):
    from mccnn_cl.importers import UNKNOWN_LICENCE

    _start(UNKNOWN_LICENCE, tmp_path=tmp_path)
    run = Weights.random(conv_layers=[[8, 3], [8, 3]], architecture="mccnn-fst", seed=2)
    run.meta["training"] = {"trained_on": {"middlebury/Venus": 10}}
    run.save(tmp_path / "run.npz")
    with pytest.raises(InputError, match="unknown.*give --licence"):
        ship.ship(tmp_path / "run.npz", tmp_path / "s.npz", "s", "paper", "d", init=tmp_path / "start.npz")
    w = ship.ship(tmp_path / "run.npz", tmp_path / "s.npz", "s", "paper", "d", init=tmp_path / "start.npz",
                  licence="MIT (mine)")
    assert w.meta["licence"] == "MIT (mine)"


def test_train_init_from_a_converted_start_writes_the_weights(shared_data, tmp_path, monkeypatch, capsys):
    """train --init a converted network whose trained_on is a list: the run exports its weights with
    the lineage (it raised ValueError in record_init after all training); and if recording the
    lineage fails anyway, the weights are still written, with the error in their provenance."""
    import json

    from mccnn_cl.importers import APACHE2
    from mccnn_cl.train import train as tr

    _start(APACHE2, ["kitti2012/000000"], tmp_path=tmp_path)
    args = ["--data", str(shared_data / "middlebury"), "--include", "middlebury/Tsukuba", "--arch", "fst",
            "--conv", json.dumps([[8, 3], [8, 3]]), "--fc", "[]", "--sampler", "crop", "--crops-per-step", "1",
            "--epochs", "1", "--steps-per-epoch", "1", "--val-pixels", "0", "--val-examples", "0", "--threads",
            "1", "--no-progress", "--init", str(tmp_path / "start.npz")]
    assert tr.main(args + ["--out", str(tmp_path / "a")]) == 0
    t = Weights.load(tmp_path / "a" / "weights.npz").meta["training"]
    assert set(t["trained_on"]) == {"kitti2012/000000", "middlebury/Tsukuba"}
    assert t["init"]["licence"] == APACHE2 and APACHE2 in ship.licence_for({"training": t})

    def broken(*a, **k):
        raise ValueError("dictionary update sequence element #0 has length 16; 2 is required")

    monkeypatch.setattr(tr, "record_init", broken)
    capsys.readouterr()
    assert tr.main(args + ["--out", str(tmp_path / "b")]) == 0
    t = Weights.load(tmp_path / "b" / "weights.npz").meta["training"]
    assert "ValueError" in t["init"]["provenance_error"] and t["init"]["licence"] == APACHE2
    assert "warning" in capsys.readouterr().err
