"""The one-command GPU training run: scripts/pack_gpu_data.sh, scripts/gpu_train.sh, --fit-minutes.

Cheap checks only (the whole rehearsal, `GPU_TRAIN_DEVICE=cpu bash
scripts/gpu_train.sh fst 1`, takes a minute; docs/training.md, "On a GPU"):
the packed folder is a layout discover() reads, with the labeled frames only;
the training entry point imports without pyopencl (the GPU image has none);
gpu_train.sh stops with one line when there is no CUDA device; the time
budget's plan fits; a --fit-minutes run is the run with the epochs it chose.
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mccnn_cl.evaluation.datasets import discover
from mccnn_cl.errors import InputError
from mccnn_cl.train.budget import Calibration, plan
from mccnn_cl.train.train import main
from mccnn_cl.weights import Weights

REPO = Path(__file__).resolve().parents[1]


def _copy(src: Path, dst: Path):
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(src, dst)


@pytest.fixture(scope="module")
def small_data(shared_data, tmp_path_factory):
    """Two labeled KITTI 2015 frames, one KITTI 2012 frame, an unlabeled KITTI 2015 frame, Cones."""
    root = tmp_path_factory.mktemp("data")
    k15, k12 = shared_data / "kitti2015" / "training", shared_data / "kitti2012" / "training"
    for frame in ("000000_10.png", "000001_10.png"):
        for d in ("image_2", "image_3", "disp_occ_0", "disp_noc_0"):
            if (k15 / d / frame).exists():
                _copy(k15 / d / frame, root / "kitti2015" / "training" / d / frame)
    for d in ("image_2", "image_3"):  # no GT: not packed
        _copy(k15 / d / "e00001_10.png", root / "kitti2015" / "training" / d / "e00001_10.png")
    for d in ("colored_0", "colored_1", "disp_occ", "disp_refl_occ"):
        _copy(k12 / d / "000000_10.png", root / "kitti2012" / "training" / d / "000000_10.png")
    shutil.copytree(shared_data / "middlebury" / "Cones", root / "middlebury" / "Cones")
    shutil.copytree(shared_data / "middlebury" / "Tsukuba", root / "middlebury" / "Tsukuba")  # not packed
    return root


@pytest.mark.full_data
def test_pack_gpu_data_gives_a_layout_discover_reads(small_data, tmp_path):
    dest = tmp_path / "packed"
    r = subprocess.run(["bash", str(REPO / "scripts" / "pack_gpu_data.sh"), str(small_data), str(dest)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "packed" in r.stdout and "KiB" in r.stdout
    keys = sorted(ref.key for ref in discover(dest, labeled=True))
    assert keys == ["kitti2012/000000", "kitti2015/000000", "kitti2015/000001", "middlebury/Cones"]
    assert sorted(ref.key for ref in discover(dest)) == keys  # the unlabeled frame stayed behind
    assert not (dest / "kitti2012" / "training" / "disp_refl_occ").exists()  # the loader does not read it
    assert (dest / "kitti2015" / "training" / "disp_noc_0" / "000000_10.png").exists()
    a = {ref.key: ref for ref in discover(small_data, labeled=True)}["kitti2015/000000"].load()
    b = {ref.key: ref for ref in discover(dest, labeled=True)}["kitti2015/000000"].load()
    np.testing.assert_array_equal(np.nan_to_num(a.disp, nan=-1), np.nan_to_num(b.disp, nan=-1))
    np.testing.assert_array_equal(a.valid_noc, b.valid_noc)
    np.testing.assert_array_equal(a.left, b.left)
    # run again: the destination is refilled, not added to
    (dest / "stray.txt").write_text("x")
    assert subprocess.run(["bash", str(REPO / "scripts" / "pack_gpu_data.sh"), str(small_data), str(dest)],
                          capture_output=True, text=True, timeout=60).returncode == 0
    assert not (dest / "stray.txt").exists()


def test_pack_gpu_data_missing_data_is_one_line(tmp_path):
    r = subprocess.run(["bash", str(REPO / "scripts" / "pack_gpu_data.sh"), str(tmp_path / "nope"),
                        str(tmp_path / "packed")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stdout == "" and len(r.stderr.strip().splitlines()) == 1 and "no data folder" in r.stderr


@pytest.mark.slow
def test_training_entry_point_needs_no_pyopencl(tmp_path):
    """The GPU image has torch but no pyopencl: importing the trainer (and its --help) must not need it."""
    (tmp_path / "sitecustomize.py").write_text("import sys\nsys.modules['pyopencl'] = None\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    code = ("import sys\n"
            "try:\n    import pyopencl\nexcept ImportError:\n    pass\n"
            "else:\n    sys.exit('pyopencl is still importable: the test would prove nothing')\n"
            "import mccnn_cl.train.train, mccnn_cl.train.budget, mccnn_cl.weights, mccnn_cl.evaluation.datasets\n"
            "mccnn_cl.train.train.build_parser().parse_args(['--data', 'x', '--out', 'y', '--fit-minutes', '1'])\n"
            "print('ok')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stdout + r.stderr


def _gpu_train(args, tmp_path, **env):
    e = {k: v for k, v in os.environ.items() if k not in ("GPU_TRAIN_DEVICE", "GPU_TRAIN_ARGS")}
    e.update(OUT=str(tmp_path / "out"), PYTHON=sys.executable, CUDA_VISIBLE_DEVICES="", **env)
    return subprocess.run(["bash", str(REPO / "scripts" / "gpu_train.sh"), *args], capture_output=True, text=True,
                          env=e, timeout=120, cwd=tmp_path)


@pytest.mark.slow
def test_gpu_train_refuses_without_cuda(tmp_path):
    r = _gpu_train(["fst", "1"], tmp_path)
    lines = (r.stdout + r.stderr).strip().splitlines()
    assert r.returncode == 3, r.stdout + r.stderr
    assert len(lines) == 1 and "no CUDA device" in lines[0] and "GPU_TRAIN_DEVICE=cpu" in lines[0], lines
    assert not (tmp_path / "out").exists()  # nothing written


def test_gpu_train_checks_its_arguments(tmp_path):
    for args, what in ((["nope"], "ARCH must be"), (["fst", "soon"], "MINUTES must be")):
        r = _gpu_train(args, tmp_path)
        assert r.returncode == 2 and what in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    for env, what in (({"GPU_TRAIN_SET": "all"}, "GPU_TRAIN_SET must be"),
                      ({"GPU_TRAIN_NAME": "a/b"}, "GPU_TRAIN_NAME must be")):
        r = _gpu_train(["fst", "1"], tmp_path, **env)
        assert r.returncode == 2 and what in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


@pytest.mark.full_data
def test_pack_families_gives_an_archive_discover_reads(small_data, tmp_path):
    """tools/pack_gpu_families.py (pack_gpu_data.sh --families): held-out pairs stay out
    but the validation ones, images are stored gray with the pixels training reads, ground
    truth within half a step of the original; the unpacked folder is a layout discover reads."""
    import tarfile

    from mccnn_cl.io import read_pfm

    out = tmp_path / "pack.tar.xz"
    r = subprocess.run(["bash", str(REPO / "scripts" / "pack_gpu_data.sh"), "--families", "--data", str(small_data),
                        "--out", str(out), "--holdout", "kitti2015/000000", "middlebury/Cones", "middlebury/Tsukuba",
                        "--val", "middlebury/Cones"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "2 training pairs" in r.stdout and "1 validation pairs" in r.stdout, r.stdout
    dest = tmp_path / "unpacked"
    with tarfile.open(out) as tar:
        tar.extractall(dest)
    keys = sorted(ref.key for ref in discover(dest, labeled=True))
    assert keys == ["kitti2012/000000", "kitti2015/000001", "middlebury/Cones"]
    a = {ref.key: ref for ref in discover(small_data, labeled=True)}
    b = {ref.key: ref for ref in discover(dest, labeled=True)}
    for key in keys:
        pa, pb = a[key].load(), b[key].load()
        assert pb.left.ndim == 2
        for x, y in zip(pa.gray(), pb.gray()):
            np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(np.isnan(pa.disp), np.isnan(pb.disp))
        assert np.nanmax(np.abs(pa.disp - pb.disp)) <= 1 / 64
    g = read_pfm(dest / "middlebury" / "Cones" / "disp0GT.pfm")
    assert np.array_equal(g[np.isfinite(g)] * 32, np.round(g[np.isfinite(g)] * 32))
    r = subprocess.run(["bash", str(REPO / "scripts" / "pack_gpu_data.sh"), "--families", "--data", str(small_data),
                        "--out", str(out), "--val", "eth3d/nowhere"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "eth3d/nowhere" in r.stderr


def test_plan_fits_the_budget():
    cal = Calibration(step_s=0.05, epoch_end_s=2.0, setup_s=3.0, export_s=0.1, checkpoint_s=0.05, steps=20)
    epochs, spe = plan(480, cal, 500, checkpoint_minutes=5)
    assert spe == 500
    per_epoch = spe * cal.step_s + cal.epoch_end_s
    fixed = cal.setup_s + 2 * cal.export_s
    assert fixed + epochs * per_epoch <= 0.9 * 480 < fixed + (epochs + 1) * per_epoch + 2 * cal.checkpoint_s
    # too little time for 2 epochs of 500 steps: the epochs shrink, the schedule still fits
    epochs, spe = plan(40, cal, 500)
    assert epochs == 2 and 1 <= spe < 500
    assert fixed + 2 * (spe * cal.step_s + cal.epoch_end_s) <= 40
    with pytest.raises(InputError, match="too short"):
        plan(5, cal, 500)


@pytest.mark.full_data
def test_fit_minutes_run_is_the_run_with_the_chosen_schedule(small_data, tmp_path, capsys):
    """--fit-minutes only chooses --epochs/--steps-per-epoch: the calibration leaves the run untouched."""
    base = ["--data", str(small_data), "--include", "kitti2015/*", "--holdout", "middlebury/Cones",
            "--arch", "fst", "--conv", "[[8, 3], [8, 3]]", "--sampler", "crop", "--augment", "--subpixel",
            "--crops-per-step", "2", "--crop", "15", "15", "--per-crop", "64", "--negatives", "2",
            "--val-pixels", "60", "--val-examples", "100", "--threads", "1", "--no-progress"]
    assert main(base + ["--fit-minutes", "0.25", "--calibrate-steps", "2", "--steps-per-epoch", "1000",
                        "--out", str(tmp_path / "fit")]) == 0
    out = capsys.readouterr().out
    assert "fit-minutes 0.25:" in out and "s/step" in out
    fit = Weights.load(str(tmp_path / "fit" / "weights.npz")).meta["training"]["fit_minutes"]
    epochs, spe = fit["epochs"], fit["steps_per_epoch"]
    assert epochs >= 2 and 1 <= spe <= 1000 and fit["calibration"]["steps"] == 2
    hist = json.loads((tmp_path / "fit" / "history.json").read_text())
    assert len(hist) == epochs
    assert main(base + ["--epochs", str(epochs), "--steps-per-epoch", str(spe), "--out", str(tmp_path / "plain")]) == 0
    a = Weights.load(str(tmp_path / "fit" / "weights.npz"))
    b = Weights.load(str(tmp_path / "plain" / "weights.npz"))
    assert len(a.conv) == len(b.conv) == 2
    for (wa, ba), (wb, bb) in zip(a.conv, b.conv):
        np.testing.assert_array_equal(wa, wb)
        np.testing.assert_array_equal(ba, bb)
    # not with --resume (the plan is for a new run)
    assert main(base + ["--fit-minutes", "1", "--resume", str(tmp_path / "plain" / "checkpoint.pt"),
                        "--out", str(tmp_path / "plain")]) == 2


@pytest.mark.full_data
def test_gpu_lease_evaluates_held_out_pairs_packed_apart(small_data, tmp_path):
    """gpu_lease.sh's evaluation (no training, on the CPU): the held-out pairs are packed
    apart from the training data (--holdout '*': no training pair in that archive), each
    SET|LABEL=SPEC entry appends its records to eval_SET.jsonl, {RUN} names the runs'
    folder, a bad SET is refused with a line, and entries past the deadline are not run."""
    import tarfile

    out = tmp_path / "eval.tar.xz"
    r = subprocess.run(["bash", str(REPO / "scripts" / "pack_gpu_data.sh"), "--families", "--data", str(small_data),
                        "--out", str(out), "--holdout", "*", "--val", "middlebury/Cones"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "0 training pairs" in r.stdout, r.stdout + r.stderr
    held = tmp_path / "held"
    with tarfile.open(out) as tar:
        tar.extractall(held)
    assert [ref.key for ref in discover(held, labeled=True)] == ["middlebury/Cones"]
    env = dict(os.environ, GPU_TRAIN_DEVICE="cpu", GPU_LEASE_RUNS="", PYTHON=sys.executable,
               GPU_LEASE_EVAL_DATA=str(held), GPU_TRAIN_DATA=str(small_data),
               GPU_LEASE_TRAIN_PAIRS="middlebury/Cones", GPU_LEASE_EVAL="heldout|c=census;nowhere|x=census",
               GPU_LEASE_EVAL_AFTER="train|n={RUN}/missing.npz", OUT=str(tmp_path / "back"))
    r = subprocess.run(["bash", str(REPO / "scripts" / "gpu_lease.sh"), "0", "0"], capture_output=True, text=True,
                       timeout=300, env=env)
    assert r.returncode == 0, r.stdout + r.stderr
    recs = [json.loads(line) for line in open(tmp_path / "back" / "eval_heldout.jsonl")]
    assert [(x["method"], x["pair"]) for x in recs] == [("c", "middlebury/Cones")]
    assert 0 <= recs[0]["result"]["bad2_noc"] < 100
    assert "SET must be train or heldout" in r.stdout
    log = (tmp_path / "back" / "eval.log").read_text()
    assert "missing.npz" in log and "{RUN}" not in log and "/gpu_lease." in log  # substituted, then failed
    env.update(GPU_LEASE_DEADLINE="0", OUT=str(tmp_path / "late"))
    r = subprocess.run(["bash", str(REPO / "scripts" / "gpu_lease.sh"), "0", "0"], capture_output=True, text=True,
                       timeout=120, env=env)
    assert r.returncode == 0 and r.stdout.count("not run (deadline)") == 2, r.stdout
    assert not (tmp_path / "late" / "eval_heldout.jsonl").exists()
