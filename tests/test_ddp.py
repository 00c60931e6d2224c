"""Distributed training (DDP under torchrun, gloo on the CPU).

One torchrun launch of 2 CPU processes (this file's ``__main__``: the
worker) trains one step per configuration (fst and paper nets, crop and
patch samplers, with and without augmentation, plus one CLI run); the tests
compare each rank's parameters with one process doing one step on the union
of the two ranks' batches (``crops_per_step`` / ``batch_size`` doubled:
:func:`mccnn_cl.train.train.train` gives rank r crops ``r*C..(r+1)*C-1`` /
locations ``r*B/2..`` of the step's draw for ``2*C`` / ``2*B``).
"""

import dataclasses
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from mccnn_cl.evaluation.datasets import load_middlebury
from mccnn_cl.errors import InputError
from mccnn_cl.train.crops import MIDDLEBURY_AUGMENT, CropSampler
from mccnn_cl.train.model import MCCNN
from mccnn_cl.train.train import ARCHS, TrainConfig, main, train
from mccnn_cl.weights import Weights

WORLD = 2
LAYERS = {"fst": ([[8, 3], [8, 3], [8, 3]], []), "paper": ([[8, 3], [16, 3], [16, 1]], [32, 32, 2])}
#: name -> (arch, sampler, extra config); augmentation covers the per-rank slice of the step's jitter
CONFIGS = {
    "fst-crop-aug": ("fst", "crop", dict(augment=True, subpixel=True)),
    "paper-crop": ("paper", "crop", {}),
    "fst-patch": ("fst", "patch", {}),
    "paper-patch-aug": ("paper", "patch", dict(augment=True)),
}
CROPS, BATCH = 2, 64  # per rank
CLI_ARGS = ["--include", "middlebury/Tsukuba", "--arch", "fst", "--sampler", "crop", "--epochs", "1",
            "--steps-per-epoch", "1", "--crop", "15", "15", "--spread", "12", "--conv", json.dumps([[8, 3]] * 3),
            "--lr", "1", "--val-examples", "0", "--val-pixels", "0", "--threads", "1", "--no-progress"]


def _cfg(name: str, scale: int = 1) -> TrainConfig:
    """The per-rank config (``scale=1``) or the single-process one on the union (``scale=WORLD``)."""
    arch, sampler, extra = CONFIGS[name]
    conv, fc = LAYERS[arch]
    # lr 1: one step moves the weights by the gradient itself, far above float rounding of the weights.
    base = dict(arch=arch, sampler=sampler, epochs=1, conv_layers=conv, fc_layers=fc, lr=1.0, seed=3,
                val_examples=0, val_pixels=0, progress=False)
    if sampler == "crop":
        base.update(steps_per_epoch=1, crops_per_step=CROPS * scale, crop=(15, 15), spread=12, per_crop=1024,
                    negatives=2, n_lo=4, n_hi=8, p_hi=1)
    else:
        base.update(batch_size=BATCH * scale, examples_per_epoch=BATCH * WORLD)  # one step
    base.update(extra)
    return TrainConfig(**base)


def _pair(data: Path):
    """Tsukuba's top 160 rows x 300 columns (its GT has a blank border: crops hold different counts)."""
    p = load_middlebury(data / "middlebury" / "Tsukuba")
    c = lambda a: None if a is None else np.ascontiguousarray(a[0:160, 0:300])  # noqa: E731
    return dataclasses.replace(p, left=c(p.left), right=c(p.right), disp=c(p.disp), valid_noc=c(p.valid_noc),
                               valid_all=c(p.valid_all))


def _worker(data: Path, out: Path) -> None:
    """One rank: every configuration's one-step run, then one CLI run."""
    import torch.distributed as dist

    from mccnn_cl.train.train import init_distributed
    torch.set_num_threads(1)
    device, created = init_distributed("cpu")
    rank = dist.get_rank()
    assert dist.get_world_size() == WORLD and dist.get_backend() == "gloo" and device.type == "cpu"
    pair = _pair(data)
    for name in CONFIGS:
        (out / name).mkdir(parents=True, exist_ok=True)
        res = train(_cfg(name), [pair], [], device, out / name, log=lambda *a: None)
        torch.save(res["model"].state_dict(), out / name / f"rank{rank}.pt")
        (out / name / f"rank{rank}.json").write_text(json.dumps(res["history"]))
    # Resume: stopped after 1 of 2 steps (a mid-epoch checkpoint, rank 0 writes, all ranks load) and resumed.
    cfg = dataclasses.replace(_cfg("fst-crop-aug"), steps_per_epoch=2, lr=0.1)
    for run, stop in (("full", None), ("resumed", 1)):
        d = out / f"resume-{run}"
        d.mkdir(parents=True, exist_ok=True)
        res = train(cfg, [pair], [], device, d, log=lambda *a: None, stop_after_steps=stop)
        if stop:
            if rank == 0:
                shutil.copy(d / "checkpoint.pt", d / "mid.pt")
            res = train(cfg, [pair], [], device, d, log=lambda *a: None, resume=d / "checkpoint.pt")
        torch.save(res["model"].state_dict(), d / f"rank{rank}.pt")
    # Interrupted: rank 1 alone gets SIGTERM during step 1 of 2; the ranks agree on it at that step's
    # all-reduce, rank 0 writes the mid-epoch checkpoint, both raise TrainingInterrupted; resumed, the
    # run equals "resume-full".
    import signal

    import mccnn_cl.train.train as T
    d = out / "interrupt"
    d.mkdir(parents=True, exist_ok=True)
    real, fired = T.crop_loss, []

    def hooked(*a, **k):
        if rank == 1 and not fired:
            fired.append(1)
            os.kill(os.getpid(), signal.SIGTERM)
        return real(*a, **k)
    T.crop_loss = hooked
    stopped = None
    try:
        train(cfg, [pair], [], device, d, log=lambda *a: None)
    except T.TrainingInterrupted as exc:
        stopped = [exc.signum, exc.epoch, exc.step, exc.code]
    finally:
        T.crop_loss = real
    (d / f"stopped{rank}.json").write_text(json.dumps(stopped))
    res = train(cfg, [pair], [], device, d, log=lambda *a: None, resume=d / "checkpoint.pt")
    torch.save(res["model"].state_dict(), d / f"rank{rank}.pt")
    assert main(["--data", str(data / "middlebury"), "--crops-per-step", str(CROPS), "--out", str(out / "cli"),
                 *CLI_ARGS]) == 0
    if created:
        dist.destroy_process_group()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ddp_out(shared_data, tmp_path_factory):
    out = tmp_path_factory.mktemp("ddp")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.setdefault("GLOO_SOCKET_IFNAME", "lo")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", f"--nproc_per_node={WORLD}",
                           "--master_addr=127.0.0.1", f"--master_port={_free_port()}", __file__, "--worker",
                           str(shared_data), str(out)], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-8000:]
    print(f"torchrun worker: {time.perf_counter() - t0:.1f} s")
    return out


@pytest.fixture(autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _init_state(cfg: TrainConfig) -> dict:
    """The weights every rank starts from (train() seeds torch with cfg.seed, then He-initialises)."""
    torch.manual_seed(cfg.seed)
    net = MCCNN(cfg.conv_layers, cfg.fc_layers, architecture=ARCHS[cfg.arch], margin=cfg.margin)
    return net.he_init_().state_dict()


def _max_rel_diff(a: dict, b: dict, p0: dict) -> float:
    """max over tensors of max|a - b| / max|b - p0|: the difference relative to the step's update."""
    return max(float((a[k] - b[k]).abs().max() / (b[k] - p0[k]).abs().max()) for k in p0)


#: Rounding, not bits: gloo sums the two ranks' gradients, the single process sums the same per-example
#: contributions in one backward in another order, and each rank's loss is rescaled by its share of the
#: step's examples; float32 results then agree to a few 1e-6 of the update (measured <= 4e-6), not
#: exactly.  A wrong batch or loss weighting moves them by >= 9e-3 (both ranks on one share; the crop
#: loss unweighted: 9e-3 paper, 2.5e-2 fst; the patch jitter drawn per rank: 1.0).
TOL = 5e-5


@pytest.mark.parametrize("name", list(CONFIGS))
@pytest.mark.slow
def test_ddp_step_equals_single_process_step_on_union(name, ddp_out, shared_data, tmp_path):
    ranks = [torch.load(ddp_out / name / f"rank{r}.pt") for r in range(WORLD)]
    for k, v in ranks[0].items():  # DDP keeps the replicas identical (same all-reduced gradient, same SGD)
        assert torch.equal(v, ranks[1][k]), k
    pair = _pair(shared_data)
    cfg = _cfg(name)
    p0 = _init_state(cfg)
    union = train(_cfg(name, WORLD), [pair], [], "cpu", tmp_path / "union", log=lambda *a: None)
    single = {k: v.detach() for k, v in union["model"].state_dict().items()}
    err = _max_rel_diff(ranks[0], single, p0)
    assert err < TOL, (name, err)
    hist = json.loads((ddp_out / name / "rank0.json").read_text())
    assert hist[0]["examples"] == union["history"][0]["examples"]          # the ranks saw the union's examples
    assert hist[0]["train_loss"] == pytest.approx(union["history"][0]["train_loss"], rel=1e-5)
    # The comparison resolves far finer than the effect of a wrong batch: one rank's share alone
    # (what a rank that ignored the other's examples would step on) is far off.
    alone = train(cfg, [pair], [], "cpu", tmp_path / "alone", log=lambda *a: None)["model"].state_dict()
    assert _max_rel_diff(ranks[0], {k: v.detach() for k, v in alone.items()}, p0) > 100 * TOL


def test_crop_ranks_hold_different_example_counts(shared_data):
    """The crop configurations test the loss weighting: the ranks' shares of the step differ in size,
    and each rank's ``take`` is exactly its slice of the full draw."""
    pair = _pair(shared_data)
    for name in ("fst-crop-aug", "paper-crop"):
        cfg = _cfg(name, WORLD)
        m = MCCNN(cfg.conv_layers, cfg.fc_layers, architecture=ARCHS[cfg.arch])
        aug = MIDDLEBURY_AUGMENT if cfg.augment else None  # train()'s choice for a Middlebury pair
        s = CropSampler([pair], m.patch_size, p_hi=cfg.p_hi, n_lo=cfg.n_lo, n_hi=cfg.n_hi, crop=cfg.crop,
                        spread=cfg.spread, per_crop=cfg.per_crop, negatives=cfg.negatives, subpixel=cfg.subpixel,
                        augment=aug)
        rng = lambda: np.random.default_rng([cfg.seed, 0, 0])  # noqa: E731  (epoch 0, step 0)
        full = s.sample(rng(), CROPS * WORLD)
        parts = [s.sample(rng(), CROPS * WORLD, take=(r * CROPS, (r + 1) * CROPS)) for r in range(WORLD)]
        assert parts[0].n != parts[1].n, name
        torch.testing.assert_close(torch.cat([p.left for p in parts]), full.left, rtol=0, atol=0)
        torch.testing.assert_close(torch.cat([p.right for p in parts]), full.right, rtol=0, atol=0)
        torch.testing.assert_close(torch.cat([p.crop + r * CROPS for r, p in enumerate(parts)]), full.crop)
        for f in ("ql", "qp", "qn"):
            torch.testing.assert_close(torch.cat([getattr(p, f) for p in parts]), getattr(full, f), rtol=0, atol=0)


def test_ddp_resumes_mid_epoch_bit_for_bit(ddp_out, shared_data, tmp_path):
    """Stopped after step 1 of 2 and resumed under torchrun: bit-identical to the uninterrupted DDP run;
    the mid-epoch checkpoint names its 2 processes and does not resume in one."""
    for r in range(WORLD):
        full = torch.load(ddp_out / "resume-full" / f"rank{r}.pt")
        resumed = torch.load(ddp_out / "resume-resumed" / f"rank{r}.pt")
        for k, v in full.items():
            assert torch.equal(v, resumed[k]), (r, k)
    mid = ddp_out / "resume-resumed" / "mid.pt"
    ck = torch.load(mid, weights_only=False)
    assert ck["world_size"] == WORLD and ck["mid"]["i"] == 1
    cfg = dataclasses.replace(_cfg("fst-crop-aug"), steps_per_epoch=2, lr=0.1)
    with pytest.raises(InputError, match="2 process"):
        train(cfg, [_pair(shared_data)], [], "cpu", tmp_path, log=lambda *a: None, resume=mid)


def test_cli_under_torchrun(ddp_out, shared_data, tmp_path):
    """torchrun + the CLI: rank 0 exports once (the torchrun command in the provenance), and the weights
    equal one process's CLI run with twice the crops per step."""
    w = Weights.load(ddp_out / "cli" / "weights.npz")
    t = w.meta["training"]
    assert t["processes"] == WORLD and t["command"].startswith(f"torchrun --nproc_per_node={WORLD} -m")
    assert json.loads((ddp_out / "cli" / "run.json").read_text())["processes"] == WORLD
    assert [(p["processes"], p["steps"]) for p in t["parts"]] == [(WORLD, [0, 1])]
    assert main(["--data", str(shared_data / "middlebury"), "--crops-per-step", str(CROPS * WORLD),
                 "--out", str(tmp_path / "one"), *CLI_ARGS]) == 0
    one = Weights.load(tmp_path / "one" / "weights.npz")
    assert one.meta["training"]["examples"] == t["examples"]
    a, b = MCCNN.from_weights(w).state_dict(), MCCNN.from_weights(one).state_dict()
    cfg = TrainConfig(arch="fst", conv_layers=[[8, 3]] * 3, fc_layers=[], seed=0)
    assert _max_rel_diff(a, b, _init_state(cfg)) < TOL


def test_ddp_signal_stops_every_rank_after_the_same_step(ddp_out):
    """SIGTERM to one rank only: both ranks stop after the same step (agreed in the step's
    all-reduce) with the mid-epoch checkpoint, and the resumed run is bit-identical to the
    uninterrupted one."""
    d = ddp_out / "interrupt"
    for r in range(WORLD):
        assert json.loads((d / f"stopped{r}.json").read_text()) == [15, 1, 1, 143], r
        full = torch.load(ddp_out / "resume-full" / f"rank{r}.pt")
        resumed = torch.load(d / f"rank{r}.pt")
        for k, v in full.items():
            assert torch.equal(v, resumed[k]), (r, k)


def test_resume_with_another_process_count_warns(ddp_out, shared_data, tmp_path, capsys):
    """The torchrun CLI run's end-of-epoch checkpoint continued by one process: allowed, with a
    warning naming both process counts, and each part's processes in the provenance."""
    capsys.readouterr()
    assert main(["--data", str(shared_data / "middlebury"), "--crops-per-step", str(CROPS), "--out",
                 str(tmp_path / "one"), *CLI_ARGS, "--epochs", "2", "--resume",
                 str(ddp_out / "cli" / "checkpoint.pt")]) == 0
    warn = [s for s in capsys.readouterr().out.splitlines() if s.startswith("warning: resuming")]
    assert warn and f"processes {WORLD} -> 1" in warn[0] and "epochs 1 -> 2" in warn[0]
    t = Weights.load(tmp_path / "one" / "weights.npz").meta["training"]
    assert [(p["processes"], p["steps"]) for p in t["parts"]] == [(WORLD, [0, 1]), (1, [1, 2])]


if __name__ == "__main__" and sys.argv[1:2] == ["--worker"]:
    _worker(Path(sys.argv[2]), Path(sys.argv[3]))
