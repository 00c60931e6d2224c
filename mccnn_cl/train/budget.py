"""Fit a crop-sampler run into a wall-clock budget: time a few steps, then choose the schedule.

``--fit-minutes M`` (:mod:`.train` CLI): before training,
:func:`mccnn_cl.train.train.calibrate` (beside the pieces of the run it times)
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
from dataclasses import dataclass

import torch

from mccnn_cl.errors import InputError

__all__ = ["Calibration", "plan"]


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


def sync_device(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


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
