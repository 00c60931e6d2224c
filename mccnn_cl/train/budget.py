"""Fit a crop-sampler run into a wall-clock budget: time a few steps, then choose the schedule.

``--fit-minutes M`` (:mod:`.train` CLI): before training, :func:`calibrate`
times ``--calibrate-steps`` SGD steps of the run's own recipe (sampler,
network, device; after a few untimed warm-up steps) on a throwaway copy of the
network, one validation on the held-out pairs, and the writes that end an
epoch (checkpoint, ``latest.npz``, the plot); :func:`plan` then chooses
``epochs`` (``steps_per_epoch`` kept, or shrunk when fewer than
``min_epochs`` epochs would fit) so that the whole planned schedule — the lr
steps are fractions of it — ends within the budget left.  The lr schedule
therefore always finishes; nothing stops the run early.  The calibration draws
its own random numbers and restores torch's, so the run is exactly the run
with the printed ``--epochs``/``--steps-per-epoch`` given.
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mccnn_cl.errors import InputError

__all__ = ["Calibration", "calibrate", "plan"]


@dataclass
class Calibration:
    step_s: float        # one SGD step: sampling, forward, backward, update
    epoch_end_s: float   # validation + checkpoint + latest.npz + plot at an epoch's end
    setup_s: float       # the sampler and the validation set, built again when training starts
    export_s: float      # one weights export (the final one)
    checkpoint_s: float  # one checkpoint.pt (also written every checkpoint_minutes within an epoch)
    steps: int           # steps timed

    def as_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def calibrate(cfg, train_pairs, val_pairs, device, steps: int = 20, warmup: int = 3) -> Calibration:
    """Time ``steps`` steps of ``cfg``'s crop-sampler recipe on ``device`` (after ``warmup`` untimed).

    Nothing of the run is touched: a fresh network and optimizer, the
    sampler's random numbers from a generator of their own, torch's global
    random state restored afterwards.
    """
    from .crops import crop_loss
    from .validation import validate
    from .train import _atomic_torch_save, _export, crop_sampler, new_model, new_optimizer, plot_history, validation_set

    if cfg.sampler != "crop":
        raise InputError("--fit-minutes times crop-sampler steps: use --sampler crop")
    if steps < 1 or warmup < 0:
        raise InputError(f"need at least one calibration step, got {steps}")
    device = torch.device(device)
    devices = [device] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(cfg.seed + 7919)
        model = new_model(cfg, device)
        opt = new_optimizer(cfg, model)
        t = time.time()
        sampler = crop_sampler(cfg, train_pairs, model.patch_size)
        vset = validation_set(cfg, val_pairs, model.patch_size)
        setup_s = time.time() - t
        rng = np.random.default_rng([cfg.seed, 2**31 - 1])  # not a step's generator (those are (seed, epoch, i))
        model.train()
        for i in range(warmup + steps):
            if i == warmup:
                _sync(device)
                t = time.time()
            loss = crop_loss(model, sampler.sample(rng, cfg.crops_per_step), device)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            float(loss.detach())  # the training loop reads the loss every step (a device sync)
        _sync(device)
        step_s = (time.time() - t) / steps
        t = time.time()
        rec = {"epoch": 1, "train_loss": float(loss.detach()), "examples": 1, "lr": cfg.lr}
        rec.update(validate(model, vset, device))
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            t_ck = time.time()
            _atomic_torch_save({"model": model.state_dict(), "optimizer": opt.state_dict()}, tmp / "checkpoint.pt")
            checkpoint_s = time.time() - t_ck
            t_exp = time.time()
            _export(model, tmp / "latest.npz", {"training": {"calibration": True}})
            export_s = time.time() - t_exp
            plot_history([rec, {**rec, "epoch": 2}], tmp / "training.png")
        epoch_end_s = time.time() - t
    return Calibration(step_s=step_s, epoch_end_s=epoch_end_s, setup_s=setup_s, export_s=export_s,
                       checkpoint_s=checkpoint_s, steps=steps)


def plan(seconds: float, cal: Calibration, steps_per_epoch: int, checkpoint_minutes: float = 5.0,
         min_epochs: int = 2, safety: float = 0.9) -> tuple[int, int]:
    """``(epochs, steps_per_epoch)`` whose schedule fits ``seconds`` of wall time.

    ``safety`` of the time left after the run's set-up and final export goes
    to the epochs (each ``steps_per_epoch`` steps plus its end: validation and
    writes), plus the mid-epoch checkpoints every ``checkpoint_minutes``.  At
    least ``min_epochs`` epochs: when fewer fit, ``steps_per_epoch`` shrinks.
    Raises :class:`InputError` when not even ``min_epochs`` one-step epochs fit.
    """
    usable = safety * (seconds - cal.setup_s - 2 * cal.export_s)
    if checkpoint_minutes > 0:
        usable -= cal.checkpoint_s * math.ceil(max(usable, 0.0) / (60.0 * checkpoint_minutes))
    per_epoch = steps_per_epoch * cal.step_s + cal.epoch_end_s
    epochs = int(usable // per_epoch) if usable > 0 else 0
    if epochs >= min_epochs:
        return epochs, steps_per_epoch
    spe = math.floor((usable - min_epochs * cal.epoch_end_s) / (min_epochs * cal.step_s)) if usable > 0 else 0
    if spe < 1:
        need = (cal.setup_s + 2 * cal.export_s + min_epochs * (cal.step_s + cal.epoch_end_s) / safety) / 60
        raise InputError(f"the time budget is too short: {min_epochs} one-step epochs need about "
                         f"{need:.1f} min here (step {cal.step_s:.2f} s, epoch end {cal.epoch_end_s:.1f} s, "
                         f"set-up {cal.setup_s:.1f} s), {seconds / 60:.1f} min left")
    return min_epochs, spe
