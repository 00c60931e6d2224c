"""Train an MC-CNN network (paper, fst or acrt) and export it for the OpenCL side.

Run as ``python -m mccnn_cl.train.train --data DIR [DIR ...] --holdout KEY ... --out runs/NAME``.

``--arch`` picks the network and its recipe defaults (``ARCH_DEFAULTS``):
paper (the CVPR paper: 2-way softmax cross-entropy, lr 0.01, N_lo 4, N_hi 8,
P_hi 1), fst (hinge loss margin 0.2, lr 0.002, offsets 1/4/10) and acrt (BCE,
lr 0.003, offsets 1/4/10), all SGD with momentum 0.9 (the released code's;
the paper states none), lr multiplied by ``lr_factor`` at ``lr_steps``
fractions of the run, He-initialised weights (see :meth:`MCCNN.he_init_`).

``--sampler patch`` trains on patch pairs (batch 128 = 64 positive + 64
negative; an epoch is ``--examples-per-epoch`` pairs drawn afresh with offsets
redrawn); ``--sampler crop`` on fully convolutional crops (:mod:`.crops`; an
epoch is ``--steps-per-epoch`` steps).  Each epoch ends with validation on
the held-out pairs (:mod:`.evaluate`), ``checkpoint.pt``, ``history.json``,
``run.json``, ``training.png``, ``latest.npz`` and, when the validation error
improves, ``best.npz``; ``checkpoint.pt`` is also written every
``--checkpoint-minutes`` within an epoch.  Every random draw derives from
``--seed`` (per epoch, and per step for crops), so a run is deterministic for
a seed and thread count, and ``--resume`` continues it bit for bit, also from
a mid-epoch checkpoint.

Launched by torchrun (``WORLD_SIZE`` > 1) it trains with
DistributedDataParallel, one process per device (gloo on the CPU, NCCL on
CUDA ``cuda:LOCAL_RANK``): each step every rank takes its own share of one
draw (``--crops-per-step`` crops, or ``--batch-size`` patch pairs, per rank),
so the ranks together train on exactly the batch one process would get with
N times as many; only rank 0 validates, logs and writes files.
"""

from __future__ import annotations

import argparse
import copy
import fnmatch
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from datetime import timedelta
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F

from mccnn_cl.evaluation.datasets import discover
from mccnn_cl.errors import InputError
from mccnn_cl.weights import ACRT, FST, PAPER, PAPER_CONV, PAPER_FC

from .crops import KITTI_AUGMENT, MIDDLEBURY_AUGMENT, CropSampler, crop_loss
from .validation import make_validation, validate
from .model import DEFAULT_LAYERS, MCCNN
from .patches import PatchSampler
from .budget import Calibration, plan, sync_device

__all__ = ["TrainConfig", "train", "select_pairs", "lr_at", "augment_batch", "init_distributed", "record_init",
           "main"]


@dataclass
class TrainConfig:
    """Every knob of a run (the CLI flags map one to one; see ``--help``)."""

    arch: str = "paper"                     # paper | fst | acrt
    epochs: int = 16
    examples_per_epoch: int | None = None   # patch pairs (pos + neg); None: all GT pixels x2
    batch_size: int = 128                   # pos + neg; must be even
    lr: float = 0.01
    lr_steps: tuple = (11 / 16, 14 / 16)    # fractions of the run where lr is multiplied by lr_factor:
    #                                         the paper's "on the 12th and 15th" epoch of 16 (1-based, as the
    #                                         released loop divides at the start of its 12th epoch)
    lr_factor: float = 0.1
    momentum: float = 0.9
    weight_decay: float = 0.0
    n_lo: int = 4
    n_hi: int = 8
    p_hi: int = 1
    gt: str = "all"                         # GT pixels making examples: "all" or "noc"
    max_per_pair: int | None = None         # cap on locations drawn from one pair per epoch
    augment: bool = False
    augment_preset: str | None = None       # crop sampler: "kitti" | "middlebury" | "family"; None: the pairs' majority
    balance: str = "pixels"                 # crop sampler: "pixels" | "pair" | "dataset" (crops per dataset alike)
    family_offsets: bool = False            # crop sampler: each dataset's offsets (FAMILY_OFFSETS[arch])
    conv_layers: list = field(default_factory=lambda: [list(c) for c in PAPER_CONV])
    fc_layers: list = field(default_factory=lambda: list(PAPER_FC))
    margin: float = 0.2                     # fst hinge margin
    sampler: str = "patch"                  # "patch" (one patch pair per example) or "crop"
    crop: tuple = (47, 47)                  # crop sampler: left feature-map size (h, w), odd
    spread: int = 32                        # crop sampler: extra right columns each side
    per_crop: int = 1024                    # crop sampler: GT pixels per crop at most
    crops_per_step: int = 2                 # crop sampler: crops per SGD step
    negatives: int = 1                      # crop sampler: negatives per GT pixel
    subpixel: bool = False                  # crop sampler: exact GT d, continuous offsets, bilinear
    steps_per_epoch: int = 500              # crop sampler: SGD steps between validations
    checkpoint_minutes: float = 5.0         # also checkpoint mid-epoch this often (wall clock)
    seed: int = 0
    val_examples: int = 4000
    val_pixels: int = 3000
    val_ndisp: int | None = None            # D for the WTA error; None: pair's ndisp or 228 (KITTI)
    progress: bool = True


ARCHS = {"paper": PAPER, "fst": FST, "acrt": ACRT}
#: per-architecture recipe defaults (released code, KITTI): lr, offsets, layers
ARCH_DEFAULTS = {
    "paper": dict(lr=0.01, n_lo=4, n_hi=8, p_hi=1, conv_layers=PAPER_CONV, fc_layers=PAPER_FC),
    "fst": dict(lr=0.002, n_lo=4, n_hi=10, p_hi=1, conv_layers=DEFAULT_LAYERS[FST][0], fc_layers=[]),
    "acrt": dict(lr=0.003, n_lo=4, n_hi=10, p_hi=1, conv_layers=DEFAULT_LAYERS[ACRT][0],
                 fc_layers=DEFAULT_LAYERS[ACRT][1]),
}


#: Per-dataset (P_hi, N_lo, N_hi) of ``--family-offsets``: the released code's KITTI recipe for
#: KITTI, its Middlebury recipe for Middlebury, MiddEval3 and ETH3D (ETH3D has none of its own).
#: The paper's network has a KITTI recipe only (CVPR paper: 1, 4, 8); its fc head is acrt's kind,
#: so the other datasets take acrt's Middlebury offsets.
FAMILY_OFFSETS = {
    "paper": {"kitti": (1, 4, 8), "middlebury": (0.5, 1.5, 18), "middeval3": (0.5, 1.5, 18),
              "eth3d": (0.5, 1.5, 18)},
    "fst": {"kitti": (1, 4, 10), "middlebury": (0.5, 1.5, 6), "middeval3": (0.5, 1.5, 6), "eth3d": (0.5, 1.5, 6)},
    "acrt": {"kitti": (1, 4, 10), "middlebury": (0.5, 1.5, 18), "middeval3": (0.5, 1.5, 18),
             "eth3d": (0.5, 1.5, 18)},
}
#: Per-dataset augmentation of ``augment_preset="family"`` (ETH3D: the Middlebury ranges).
FAMILY_AUGMENT = {"kitti": KITTI_AUGMENT, "middlebury": MIDDLEBURY_AUGMENT, "middeval3": MIDDLEBURY_AUGMENT,
                  "eth3d": MIDDLEBURY_AUGMENT}


#: Settings a resumed run may change without changing what it computes.
RESUME_FREE = ("progress", "checkpoint_minutes")


def resume_changes(saved: dict, cfg: TrainConfig) -> str:
    """The settings in which ``cfg`` differs from a checkpoint's ``config`` ("epochs 16 -> 5, seed 0 -> 1"),
    "" when none (besides :data:`RESUME_FREE`)."""
    now = asdict(cfg)
    norm = lambda v: json.loads(json.dumps(v))  # noqa: E731 - tuples as lists, as the checkpoint holds them
    diffs = [f"{k} {saved[k]!r} -> {now[k]!r}" for k in now
             if k not in RESUME_FREE and k in saved and norm(saved[k]) != norm(now[k])]
    return ", ".join(diffs)


def lr_at(cfg: TrainConfig, it: int, total: int) -> float:
    """Learning rate at iteration ``it`` of ``total``: ``lr * lr_factor ** (#steps passed)``."""
    passed = sum(1 for s in cfg.lr_steps if it >= round(s * total))
    return cfg.lr * cfg.lr_factor ** passed


# -- augmentation (optional; from the released code, see NOTES.md) ---------------

def augment_batch(left: torch.Tensor, right: torch.Tensor, gen: torch.Generator,
                  rotate: float = 7.0, scale: float = 0.9, shear: float = 0.1,
                  brightness: float = 0.7, contrast: float = 1.3, right_brightness: float = 0.3,
                  rows: torch.Tensor | None = None, n_draw: int | None = None):
    """Random geometric and photometric jitter of patch pairs (N, 1, P, P), in torch.

    Per pair one affine map (rotation up to ``rotate`` degrees, horizontal
    scale in [scale, 1], horizontal shear up to ``shear``) about the patch
    centre, applied to both patches (bilinear, border replicated; patches are
    the network's own 9x9, so corners sample the nearest edge), brightness
    ``+U(-b, b)`` and contrast ``*exp(U(-log c, log c))`` on the normalised
    intensities, and an extra ``U(-rb, rb)`` brightness on the right patch.
    The released code's ranges (NOTES.md) applied to normalised patches.

    ``rows``/``n_draw`` (distributed training): the parameters are drawn for a
    batch of ``n_draw`` pairs and those at ``rows`` (a CPU index tensor, one
    per pair given) are applied, so each rank jitters its share of a step's
    batch exactly as one process would jitter the whole batch.
    """
    n = left.shape[0]
    dev = left.device

    def u(lo, hi):
        if rows is None:
            return torch.rand(n, generator=gen).to(dev) * (hi - lo) + lo
        return torch.rand(n_draw, generator=gen)[rows].to(dev) * (hi - lo) + lo
    th = u(-rotate, rotate) * math.pi / 180
    sx = u(scale, 1.0)
    sh = u(-shear, shear)
    cos, sin = torch.cos(th), torch.sin(th)
    # theta maps output coords to input coords: R(th) @ [[sx, sh], [0, 1]]
    a = torch.stack([torch.stack([cos * sx, cos * sh - sin], 1),
                     torch.stack([sin * sx, sin * sh + cos], 1)], 1)
    theta = torch.cat([a, torch.zeros(n, 2, 1, device=dev)], 2)
    grid = F.affine_grid(theta, list(left.shape), align_corners=True)
    left = F.grid_sample(left, grid, mode="bilinear", padding_mode="border", align_corners=True)
    right = F.grid_sample(right, grid, mode="bilinear", padding_mode="border", align_corners=True)
    b = u(-brightness, brightness).view(n, 1, 1, 1)
    c = torch.exp(u(-math.log(contrast), math.log(contrast))).view(n, 1, 1, 1)
    rb = u(-right_brightness, right_brightness).view(n, 1, 1, 1)
    return left * c + b, right * c + b + rb


# -- data selection ----------------------------------------------------------

def _matches(key: str, patterns) -> bool:
    return any(fnmatch.fnmatchcase(key, p) or key.split("/", 1)[-1] == p for p in patterns)


def select_pairs(data_roots, holdout=(), include=("*",), dataset=None):
    """Discover pairs under ``data_roots``; split them into (train refs, held-out refs).

    ``holdout``/``include``: keys ``kind/name`` or fnmatch patterns
    (``kitti2015/000000``, ``middlebury/*``); a held-out pair is never
    trained on, even if ``include`` matches it.
    """
    refs = []
    for root in data_roots:
        refs.extend(discover(root, dataset, labeled=True))  # examples need ground truth
    seen, uniq = set(), []
    for r in refs:
        if r.key not in seen:
            seen.add(r.key)
            uniq.append(r)
    held = [r for r in uniq if _matches(r.key, holdout)]
    for p in holdout:
        if not any(_matches(r.key, [p]) for r in uniq):
            raise InputError(f"--holdout {p!r} matches no pair under {', '.join(map(str, data_roots))}")
    train_refs = [r for r in uniq if r not in held and _matches(r.key, include)]
    if not train_refs:
        raise InputError("no training pairs left after --include/--holdout")
    return train_refs, held


# -- distributed training (torchrun) ---------------------------------------------

#: how long a rank waits for the others at a collective (rank 0 validates and
#: writes files at each epoch's end while the others wait at a barrier)
DIST_TIMEOUT = timedelta(minutes=60)


def init_distributed(device=None):
    """Join the process group when launched by torchrun (``WORLD_SIZE`` > 1).

    Returns ``(device, created)``: the device this process trains on (on CUDA
    ``cuda:LOCAL_RANK``, whatever index ``device`` names; default CUDA when
    available, else the CPU) and whether this call created the process group
    (the caller then destroys it).  Backend: NCCL on CUDA, gloo on the CPU.
    Without torchrun (or with one process) nothing is initialised.
    """
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return device, False
    if not dist.is_available():
        raise InputError("WORLD_SIZE > 1 but this torch build has no torch.distributed")
    if device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    if dist.is_initialized():
        return device, False
    dist.init_process_group("nccl" if device.type == "cuda" else "gloo", timeout=DIST_TIMEOUT)
    return device, True


def _rank_world():
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


class _StepLoss(torch.nn.Module):
    """``forward(fn, *args) = fn(net, *args)``: the step's loss as a forward pass, so that
    DistributedDataParallel sees it (the crop loss calls the net's parts, not its forward)."""

    def __init__(self, net):
        super().__init__()
        self.net = net

    def forward(self, fn, *args):
        return fn(self.net, *args)


def _patch_loss(net, left, right):
    """Loss of a patch batch laid out as positives, then negatives (``PatchSampler.batch``)."""
    out = net(left, right)
    h = out.shape[0] // 2
    return net.loss(out[:h], out[h:])


# -- the loop ------------------------------------------------------------------

def _atomic_json(obj, path: Path) -> None:
    """``obj`` as indented JSON at ``path``, whole or not at all (:func:`mccnn_cl.atomic.atomic_write`)."""
    from ..atomic import atomic_write

    def write(tmp):
        with open(tmp, "w") as f:
            json.dump(obj, f, indent=1)
    atomic_write(path, write)


def _atomic_torch_save(obj, path: Path):
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def plot_history(history: list, path, title: str = "MC-CNN training", loss_name: str = "cross-entropy") -> None:
    """PNG of train/val loss (left axis) and val WTA 3-px error (right axis) per epoch."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ep = [h["epoch"] for h in history]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(ep, [h["train_loss"] for h in history], "o-", label="train loss")
    if any("val_loss" in h for h in history):
        ax.plot(ep, [h.get("val_loss", np.nan) for h in history], "s-", label="val loss (held-out patches)")
    ax.set_xlabel("epoch")
    ax.set_ylabel(loss_name)
    ax.grid(alpha=0.3)
    lines, labels = ax.get_legend_handles_labels()
    if any("val_err3" in h for h in history):
        ax2 = ax.twinx()
        ax2.plot(ep, [100 * h.get("val_err3", np.nan) for h in history], "^-", color="tab:red",
                 label="val WTA 3-px error (%)")
        ax2.set_ylabel("WTA 3-px error on raw CNN cost (%)")
        l2, lab2 = ax2.get_legend_handles_labels()
        lines, labels = lines + l2, labels + lab2
    ax.legend(lines, labels, loc="upper right", fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    tmp = str(path) + ".tmp.png"
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)


def _machine(device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{cpu}, {torch.get_num_threads()} torch thread(s)"


def _export(model, path: Path, meta: dict) -> None:
    """Write the weights .npz atomically (a reader never sees half a file)."""
    tmp = path.with_name(path.name + ".tmp.npz")
    copy.deepcopy(model).cpu().to_weights(meta).save(tmp)  # a copy: the trained (maybe DDP-held) net stays put
    os.replace(tmp, path)


def crop_sampler(cfg: TrainConfig, train_pairs, patch_size: int) -> CropSampler:
    """The run's :class:`CropSampler` (augmentation ranges: ``cfg.augment_preset``, else the pairs' majority)."""
    aug = None
    if cfg.augment and cfg.augment_preset == "family":
        aug = dict(FAMILY_AUGMENT)
    elif cfg.augment:
        kitti = sum(p.key.startswith("kitti") for p in train_pairs) * 2 >= len(train_pairs)
        if cfg.augment_preset is not None:
            kitti = {"kitti": True, "middlebury": False}[cfg.augment_preset]
        aug = KITTI_AUGMENT if kitti else MIDDLEBURY_AUGMENT
    offsets = None
    if cfg.family_offsets:
        if cfg.arch not in FAMILY_OFFSETS:
            raise InputError(f"--family-offsets: no per-dataset offsets for {cfg.arch}")
        offsets = FAMILY_OFFSETS[cfg.arch]
    return CropSampler(train_pairs, patch_size, p_hi=cfg.p_hi, n_lo=cfg.n_lo, n_hi=cfg.n_hi,
                       crop=tuple(cfg.crop), spread=cfg.spread, per_crop=cfg.per_crop,
                       negatives=cfg.negatives, subpixel=cfg.subpixel, augment=aug, use=cfg.gt,
                       max_per_pair=cfg.max_per_pair, balance=cfg.balance, offsets=offsets)


def new_model(cfg: TrainConfig, device):
    """``cfg``'s network, He-initialised (torch's global generator), on ``device``."""
    return MCCNN(cfg.conv_layers, cfg.fc_layers, architecture=ARCHS[cfg.arch],
                 margin=cfg.margin).he_init_().to(device)


def new_optimizer(cfg: TrainConfig, model):
    """The run's SGD (lr, momentum, weight decay of ``cfg``; the lr is set per step)."""
    return torch.optim.SGD(model.parameters(), lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)


def validation_set(cfg: TrainConfig, pairs, patch_size: int):
    """The fixed held-out examples and pixels a run validates on each epoch."""
    return make_validation(pairs, patch_size, n_examples=cfg.val_examples, n_pixels=cfg.val_pixels,
                           seed=cfg.seed + 1, n_lo=int(round(cfg.n_lo)), n_hi=int(round(cfg.n_hi)),
                           p_hi=int(round(cfg.p_hi)), ndisp=cfg.val_ndisp)


def calibrate(cfg, train_pairs, val_pairs, device, steps: int = 20, warmup: int = 3) -> Calibration:
    """Time ``steps`` steps of ``cfg``'s crop-sampler recipe on ``device`` (after ``warmup`` untimed).

    Nothing of the run is touched: a fresh network and optimizer, the
    sampler's random numbers from a generator of their own, torch's global
    random state restored afterwards.
    """
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
                sync_device(device)
                t = time.time()
            loss = crop_loss(model, sampler.sample(rng, cfg.crops_per_step), device)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            float(loss.detach())  # the training loop reads the loss every step (a device sync)
        sync_device(device)
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


def train(cfg: TrainConfig, train_pairs, val_pairs, device, out_dir, resume=None, log=print,
          stop_after: int | None = None, stop_after_steps: int | None = None, init=None) -> dict:
    """Train on ``train_pairs`` (StereoPairs with GT), validate on ``val_pairs`` each epoch.

    Writes ``checkpoint.pt`` (every epoch and every ``cfg.checkpoint_minutes``
    within one), ``history.json``, ``run.json`` (progress: step, examples,
    wall time), ``training.png``, ``latest.npz`` (weights after each epoch)
    and ``best.npz`` (whenever the validation WTA error improves) in
    ``out_dir``.  ``resume``: a checkpoint path to continue from (bit for bit,
    also from a mid-epoch checkpoint).  ``stop_after``: run at most this many
    epochs in this call; ``stop_after_steps``: stop (with a checkpoint) after
    this many steps in this call (the schedule still spans ``cfg.epochs``).
    ``init``: a :class:`~mccnn_cl.weights.Weights` of ``cfg``'s layers to start
    from instead of He initialisation (fine-tuning; :mod:`.selftrain`).
    Returns ``{"model": MCCNN (on device), "history": [...], "provenance": {...}}``.

    Inside an initialised process group of N > 1 ranks (:func:`init_distributed`)
    this is one rank of a DistributedDataParallel run: every rank draws the
    same step plan and takes its share (crop sampler: crops ``rank * C ..
    (rank + 1) * C - 1`` of the step's ``N * C`` crops, ``C`` =
    ``crops_per_step``; patch sampler: locations ``rank * B/2 ..`` of the
    step's ``N * B/2``, ``B`` = ``batch_size``, with the augmentation drawn for
    the whole step), so the ranks together train on exactly the batch of one
    process with ``N * C`` crops / batch ``N * B``.  Each rank's mean loss is
    weighted by ``N * n_rank / n_step`` (its share of the step's examples), so
    DDP's gradient average is the gradient of the step's mean loss, also when
    the ranks' crops hold different numbers of examples.  Only rank 0
    validates, logs and writes files; the others wait at a barrier after each
    epoch.  All ranks load ``resume``.
    """
    if cfg.arch not in ARCHS:
        raise InputError(f"unknown architecture {cfg.arch!r} (expected one of {', '.join(ARCHS)})")
    if cfg.sampler not in ("patch", "crop"):
        raise InputError(f"sampler must be 'patch' or 'crop', got {cfg.sampler!r}")
    if cfg.sampler == "patch" and (cfg.batch_size < 2 or cfg.batch_size % 2):
        raise InputError(f"batch size must be even (half positive, half negative), got {cfg.batch_size}")
    device = torch.device(device)
    rank, world = _rank_world()
    lead = rank == 0
    if not lead:
        log = lambda *a, **k: None  # noqa: E731
    out_dir = Path(out_dir)
    if lead:
        out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    model = new_model(cfg, device)
    if init is not None:
        if init.conv_layers() != cfg.conv_layers or init.fc_layers() != cfg.fc_layers \
                or init.architecture != ARCHS[cfg.arch]:
            raise InputError(f"init weights ({init.architecture}) do not have the run's layers ({cfg.arch})")
        model.load_state_dict(MCCNN.from_weights(init).state_dict())
    opt = new_optimizer(cfg, model)
    half = cfg.batch_size // 2
    if cfg.sampler == "patch":
        sampler = PatchSampler(train_pairs, patch_size=model.patch_size, n_lo=cfg.n_lo, n_hi=cfg.n_hi,
                               p_hi=cfg.p_hi, use=cfg.gt, max_per_pair=cfg.max_per_pair)
        per_epoch_locs = sum(sampler.locations_per_epoch().values())
        locs = per_epoch_locs if cfg.examples_per_epoch is None else cfg.examples_per_epoch // 2
        step_locs = half * world  # locations per step, all ranks together
        iters_per_epoch = max(1, locs // step_locs)
        unit = f"{cfg.batch_size} examples"
    else:
        sampler = crop_sampler(cfg, train_pairs, model.patch_size)
        per_epoch_locs = sum(sampler.counts().values())
        iters_per_epoch = cfg.steps_per_epoch
        unit = f"{cfg.crops_per_step} crops"
    if world > 1:
        unit = f"{world} processes x {unit}"
    vset = validation_set(cfg, val_pairs if lead else [], model.patch_size)
    total_iters = cfg.epochs * iters_per_epoch
    history, start_epoch, start_i, elapsed0, examples0 = [], 0, 0, 0.0, 0
    mid = None
    best = float("inf")
    if resume is not None:
        ck = torch.load(resume, map_location=device, weights_only=False)
        c = ck["config"]
        if (c["conv_layers"] != cfg.conv_layers or c["fc_layers"] != cfg.fc_layers
                or c.get("arch", "paper") != cfg.arch):
            raise InputError(f"{resume}: checkpoint has another architecture")
        if ck.get("mid") is not None and ck.get("world_size", 1) != world:
            raise InputError(f"{resume}: a mid-epoch checkpoint of a run with {ck.get('world_size', 1)} "
                             f"process(es): resume it with as many (here {world}), or from an epoch's end")
        changed = resume_changes(c, cfg)
        if changed:  # allowed (e.g. a shorter schedule when the machine slows), never silent
            log(f"warning: resuming {resume} with settings the run did not start with ({changed}): "
                "the result is not the one an uninterrupted run would give")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        history, elapsed0 = ck["history"], ck.get("elapsed", 0.0)
        examples0 = ck.get("examples_seen", sum(h["examples"] for h in history))
        best = ck.get("best_err3", float("inf"))
        mid = ck.get("mid")
        if mid is not None:
            start_epoch, start_i = mid["epoch"], mid["i"]
            log(f"resumed from {resume} in epoch {start_epoch + 1}, step {start_i}")
        else:
            start_epoch = ck["epoch"] + 1
            log(f"resumed from {resume} after epoch {ck['epoch'] + 1}")
    log(f"{cfg.arch} net, {cfg.sampler} sampler: training on {len(train_pairs)} pairs ({', '.join(sampler.keys)}), "
        f"{per_epoch_locs} GT locations; validating on {', '.join(vset.keys) or 'nothing'}")
    log(f"{cfg.epochs} epochs x {iters_per_epoch} steps x {unit}; device {device}"
        + (f" (rank 0 of {world}, {dist.get_backend()})" if world > 1 else ""))
    step_net = None
    if world > 1:
        # After init/resume (all ranks hold the same weights; DDP broadcasts rank 0's anyway).
        step_net = torch.nn.parallel.DistributedDataParallel(_StepLoss(model))
        ar = torch.arange(half)
        aug_rows = torch.cat([rank * half + ar, step_locs + rank * half + ar]) if cfg.sampler == "patch" else None
    t_start = time.time()
    examples_seen = examples0
    steps_left = stop_after_steps
    last_ck = time.time()

    def progress(step_epoch, step_i):
        return {"arch": cfg.arch, "sampler": cfg.sampler, "epoch": step_epoch, "step": step_epoch * iters_per_epoch
                + step_i, "total_steps": total_iters, "examples_seen": int(examples_seen),
                "wall_time_s": round(elapsed0 + time.time() - t_start, 1), "best_val_err3": best,
                "updated_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                **({"processes": world} if world > 1 else {})}

    def save_ck(epoch, mid_state):
        _atomic_torch_save({"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch,
                            "history": history, "config": asdict(cfg), "elapsed": elapsed0 + time.time() - t_start,
                            "examples_seen": examples_seen, "best_err3": best, "mid": mid_state,
                            "world_size": world},
                           out_dir / "checkpoint.pt")
        _atomic_json(progress(mid_state["epoch"] if mid_state else epoch + 1, mid_state["i"] if mid_state else 0),
                     out_dir / "run.json")

    end_epoch = cfg.epochs if stop_after is None else min(cfg.epochs, start_epoch + stop_after)
    stopped = False
    for epoch in range(start_epoch, end_epoch):
        rng = np.random.default_rng([cfg.seed, epoch])
        gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
        if cfg.sampler == "patch":
            plan = sampler.epoch(rng, n_locations=iters_per_epoch * step_locs)
            n_it = min(iters_per_epoch, len(plan[0]) // step_locs)
        else:
            n_it = iters_per_epoch
        i0, loss_sum, seen, t0 = 0, 0.0, 0, time.time()
        if mid is not None and mid["epoch"] == epoch:
            i0, loss_sum, seen = mid["i"], mid["loss_sum"], mid["seen"]
            gen.set_state(mid["gen"])
            mid = None
        model.train()
        bar = None
        if cfg.progress and lead:
            from tqdm import tqdm
            bar = tqdm(total=n_it, initial=i0, desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="it",
                       mininterval=1.0 if sys.stderr.isatty() else 30.0, leave=False)
        seen_here, t_here = 0, time.time()
        for i in range(i0, n_it):
            it = epoch * iters_per_epoch + i
            lr = lr_at(cfg, it, total_iters)
            for g in opt.param_groups:
                g["lr"] = lr
            if cfg.sampler == "patch":
                s0 = i * step_locs + rank * half  # this rank's share of the step's locations
                b = sampler.batch(plan, s0, s0 + half)
                left = torch.from_numpy(b.left).to(device)
                right = torch.from_numpy(b.right).to(device)
                if cfg.augment:
                    if world > 1:  # the whole step's jitter drawn, this rank's rows applied
                        left, right = augment_batch(left, right, gen, rows=aug_rows, n_draw=2 * step_locs)
                    else:
                        left, right = augment_batch(left, right, gen)
                step = (_patch_loss, left, right)
                n_ex = len(b.labels)
            else:
                cps = cfg.crops_per_step
                cb = sampler.sample(np.random.default_rng([cfg.seed, epoch, i]), cps * world,
                                    take=None if world == 1 else (rank * cps, (rank + 1) * cps))
                step = (crop_loss, cb, device)
                n_ex = cb.n * (1 + cfg.negatives)
            if step_net is None:
                loss = step[0](model, *step[1:])
                step_loss, n_step = None, n_ex
            else:
                loss = step_net(*step)
                # The step's example count and loss sum over all ranks; weighting each rank's mean
                # loss by N * n_ex / n_step makes DDP's gradient average the gradient of the step's
                # mean loss (the crop loss averages over a count proportional to n_ex).
                tot = torch.tensor([float(n_ex), float(loss.detach()) * n_ex], dtype=torch.float64, device=device)
                dist.all_reduce(tot)
                n_tot, loss_tot = tot.tolist()
                loss = loss * (world * n_ex / n_tot)
                step_loss, n_step = loss_tot / n_tot, int(round(n_tot))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            loss_sum += (float(loss.detach()) if step_loss is None else step_loss) * n_step
            seen += n_step
            seen_here += n_step
            examples_seen += n_step
            if bar is not None:
                bar.update(1)
                if i % 50 == 0:
                    bar.set_postfix(loss=f"{loss_sum / seen:.4f}", ex_s=f"{seen_here / (time.time() - t_here):.0f}",
                                    lr=f"{lr:g}")
            last = i + 1 == n_it
            if steps_left is not None:
                steps_left -= 1
            if lead and not last and (time.time() - last_ck > 60 * cfg.checkpoint_minutes or steps_left == 0):
                save_ck(epoch - 1, {"epoch": epoch, "i": i + 1, "loss_sum": loss_sum, "seen": seen,
                                    "gen": gen.get_state()})
                last_ck = time.time()
                log(json.dumps({"checkpoint": progress(epoch, i + 1),
                                "train_loss_so_far": round(loss_sum / max(seen, 1), 5)}))
            if steps_left == 0 and not last:
                stopped = True
                break
        if bar is not None:
            bar.close()
        if stopped:
            break
        train_time = time.time() - t0
        rec = {"epoch": epoch + 1, "train_loss": loss_sum / max(seen, 1), "examples": seen,
               "lr": lr_at(cfg, epoch * iters_per_epoch + max(n_it - 1, 0), total_iters),
               "examples_per_s": seen_here / max(time.time() - t_here, 1e-9)}
        if not lead:  # rank 0 validates and writes; the others wait at the barrier below
            rec["examples_seen"] = int(examples_seen)
            history.append(rec)
        else:
            tv = time.time()
            rec.update(validate(model, vset, device))
            rec["val_time_s"] = time.time() - tv
            rec["examples_seen"] = int(examples_seen)
            rec["wall_time_s"] = round(elapsed0 + time.time() - t_start, 1)
            history.append(rec)
            err = rec.get("val_err3")
            improved = err is not None and err < best
            if improved:
                best = err
            snap = {"training": {"arch": cfg.arch, "epoch": epoch + 1, "examples_seen": int(examples_seen),
                                 "wall_time_s": rec["wall_time_s"], "held_out": vset.keys,
                                 "trained_on": {k: int(v) for k, v in sampler.counts().items()},
                                 "validation": {k: v for k, v in rec.items() if k.startswith("val_")},
                                 "config": {k: v for k, v in asdict(cfg).items() if k != "progress"}}}
            _export(model, out_dir / "latest.npz", snap)
            if improved:
                _export(model, out_dir / "best.npz", snap)
            save_ck(epoch, None)
            last_ck = time.time()
            _atomic_json(history, out_dir / "history.json")
            plot_history(history, out_dir / "training.png",
                         title=f"MC-CNN-{cfg.arch} training ({cfg.sampler} sampler)",
                         loss_name={"paper": "cross-entropy", "fst": "hinge loss",
                                    "acrt": "binary cross-entropy"}[cfg.arch])
            log(json.dumps({k: (round(v, 5) if isinstance(v, float) else v) for k, v in rec.items()}))
        if world > 1:
            dist.barrier()
        if steps_left == 0:
            break
    if world > 1:
        dist.barrier()  # rank 0's files (also a mid-epoch checkpoint at a stop) are written when train returns
    elapsed = elapsed0 + (time.time() - t_start)
    prov = {
        "architecture": ARCHS[cfg.arch],
        "trained_on": {k: int(v) for k, v in sampler.counts().items()},
        "held_out": vset.keys,
        "epochs": cfg.epochs,
        "epochs_done": len(history),
        "examples": int(examples_seen),
        "iterations": total_iters,
        **({"processes": world, "batch_per_step": (f"{world} x {cfg.crops_per_step} crops" if cfg.sampler == "crop"
                                                  else f"{world} x {cfg.batch_size} examples")}
           if world > 1 else {}),
        "wall_time_s": round(elapsed, 1),
        "machine": _machine(device) if world == 1 else f"{world} processes x {_machine(device)}",
        "torch": torch.__version__,
        "config": {k: v for k, v in asdict(cfg).items() if k != "progress"},
        "final_validation": {k: v for k, v in (history[-1] if history else {}).items()
                             if k.startswith("val_")},
    }
    return {"model": model, "history": history, "provenance": prov}


def pairs_of(value) -> dict:
    """A provenance's ``trained_on`` as this project's form, a dict pair key -> description
    (train.py: examples; the importers: who trained on it): a dict as it is, a list of keys (what
    converters of older versions wrote) with None for the description, nothing as {}."""
    if value is None:
        return {}
    if isinstance(value, dict):
        return {str(k): v for k, v in value.items()}
    if isinstance(value, str):
        return {value: None}
    if isinstance(value, (list, tuple, set)):
        return {str(k): None for k in value}
    raise TypeError(f"trained_on is a {type(value).__name__}, expected a dict of pair keys or a list of them")


def record_init(prov: dict, init, spec: str) -> dict:
    """Add a fine-tuning run's lineage to its provenance ``prov`` (in place; returned).

    ``prov["init"]`` names the starting weights ``init`` (``spec`` as given)
    with a summary of their own training, their licence and source (a
    converted network's file and sha256: :func:`mccnn_cl.train.ship.licence_for`
    carries that licence on), and ``prov["trained_on"]`` becomes every pair the
    weights have learnt from (the start's pairs, then this run's), so that
    ``mccnn-cl evaluate`` never calls a pair the start was trained on "held
    out"; this run's own pairs stay in ``trained_on_this_run``.  The start's
    ``trained_on`` may be a dict or a list of keys (older converted files).
    """
    it = init.meta.get("training") if isinstance(init.meta.get("training"), dict) else {}
    prov["init"] = {"weights": str(spec), "name": init.meta.get("name"),
                    **{k: it[k] for k in ("command", "trained_on", "held_out", "examples", "wall_time_s",
                                          "git_commit", "init", "by", "data", "source_training") if k in it},
                    **{k: init.meta[k] for k in ("licence", "source") if init.meta.get(k) is not None}}
    own = pairs_of(prov.get("trained_on"))
    merged = pairs_of(it.get("trained_on"))
    merged.update(own)
    prov["trained_on_this_run"] = own
    prov["trained_on"] = merged
    return prov


# -- CLI -------------------------------------------------------------------------

def _parse_layers(text: str):
    return json.loads(text)


def build_parser() -> argparse.ArgumentParser:
    d = TrainConfig()
    p = argparse.ArgumentParser(prog="python -m mccnn_cl.train.train", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    g = p.add_argument_group("data")
    g.add_argument("--data", nargs="+", required=True,
                   help="dataset folders: KITTI 2012/2015 roots or training/ dirs, MiddEval3 scenes or "
                        "folders of scenes, or a folder holding several of these")
    g.add_argument("--dataset", choices=["kitti2012", "kitti2015", "middlebury", "eth3d"], default=None,
                   help="keep only pairs of this kind")
    g.add_argument("--include", nargs="+", default=["*"], help="pairs to train on (keys kind/name or patterns)")
    g.add_argument("--holdout", nargs="*", default=[],
                   help="pairs never trained on, used for validation (e.g. kitti2015/000000 middlebury/Cones)")
    g.add_argument("--gt", choices=["all", "noc"], default=d.gt, help="GT pixels that make examples")
    g.add_argument("--max-per-pair", type=int, default=None,
                   help="cap on the locations one pair contributes per epoch (keeps one big image from "
                        "drowning the rest)")
    g = p.add_argument_group("recipe (defaults per --arch: paper lr 0.01, offsets 1/4/8; fst lr 0.002, hinge "
                             "margin 0.2, offsets 1/4/10, 4 conv 3x3 of 64; acrt lr 0.003, BCE, offsets 1/4/10, "
                             "4 conv 3x3 of 112, fc 384 x4 + 1)")
    g.add_argument("--arch", choices=list(ARCHS), default=d.arch, help="network: paper (CVPR 2015), fst, acrt (JMLR)")
    g.add_argument("--epochs", type=int, default=d.epochs)
    g.add_argument("--examples-per-epoch", type=int, default=None,
                   help="patch sampler: patch pairs per epoch (positives + negatives); "
                        "default: two per usable GT pixel")
    g.add_argument("--batch-size", type=int, default=d.batch_size, help="patch sampler: half positive, half negative")
    g.add_argument("--lr", type=float, default=None, help="learning rate (default: the architecture's)")
    g.add_argument("--lr-steps", type=float, nargs="*", default=list(d.lr_steps),
                   help="fractions of the run where the learning rate is multiplied by --lr-factor")
    g.add_argument("--lr-factor", type=float, default=d.lr_factor)
    g.add_argument("--momentum", type=float, default=d.momentum, help="0.9 as in the released code; 0 = plain SGD")
    g.add_argument("--weight-decay", type=float, default=d.weight_decay)
    g.add_argument("--margin", type=float, default=d.margin, help="fst hinge-loss margin")
    g.add_argument("--n-lo", type=float, default=None, help="false1: smallest negative offset")
    g.add_argument("--n-hi", type=float, default=None, help="false2: largest negative offset")
    g.add_argument("--p-hi", type=float, default=None, help="true1: largest positive offset")
    g.add_argument("--augment", action=argparse.BooleanOptionalAction, default=d.augment,
                   help="geometric/photometric jitter of the released code (not in the paper)")
    g.add_argument("--augment-preset", choices=["kitti", "middlebury", "family"], default=None,
                   help="crop sampler: augmentation ranges; family: each dataset's (KITTI's for KITTI, "
                        "Middlebury's for the others); default: the training pairs' majority")
    g.add_argument("--family-offsets", action="store_true",
                   help="crop sampler (--subpixel): each dataset's P_hi/N_lo/N_hi (KITTI 1/4/10, the others "
                        "the released Middlebury recipe: fst 0.5/1.5/6, acrt 0.5/1.5/18)")
    g.add_argument("--conv", type=_parse_layers, default=None, help="JSON [[maps, kernel], ...]")
    g.add_argument("--fc", type=_parse_layers, default=None, help="JSON [units, ..., outputs] ([] for fst)")
    g = p.add_argument_group("sampler")
    g.add_argument("--sampler", choices=["patch", "crop"], default=d.sampler,
                   help="patch: one patch pair per example; crop: fully convolutional crops (train/crops.py)")
    g.add_argument("--crop", type=int, nargs=2, default=list(d.crop), metavar=("H", "W"),
                   help="crop sampler: left feature-map size (odd)")
    g.add_argument("--spread", type=int, default=d.spread, help="crop sampler: extra right columns each side")
    g.add_argument("--per-crop", type=int, default=d.per_crop, help="crop sampler: GT pixels per crop at most")
    g.add_argument("--crops-per-step", type=int, default=d.crops_per_step)
    g.add_argument("--balance", choices=["pixels", "pair", "dataset"], default=d.balance,
                   help="crop sampler: draw crops in proportion to each pair's GT pixels (capped by "
                        "--max-per-pair), every pair alike, or every dataset (kitti, middlebury, middeval3, "
                        "eth3d) alike with its pairs by capped GT pixels")
    g.add_argument("--negatives", type=int, default=d.negatives, help="crop sampler: negatives per GT pixel")
    g.add_argument("--subpixel", action=argparse.BooleanOptionalAction, default=d.subpixel,
                   help="crop sampler: exact GT disparity and continuous offsets (bilinear feature sampling)")
    g.add_argument("--steps-per-epoch", type=int, default=d.steps_per_epoch,
                   help="crop sampler: SGD steps per epoch (validation, checkpoint and exports after each)")
    g = p.add_argument_group("run")
    g.add_argument("--out", required=True, help="run folder (checkpoint, history, plot)")
    g.add_argument("--export", default=None, help="weights .npz to write at the end (default OUT/weights.npz)")
    g.add_argument("--resume", default=None, help="checkpoint.pt to continue from")
    g.add_argument("--init", default=None, metavar="WEIGHTS",
                   help="start from these weights (.npz or a shipped name, same layers) instead of He init")
    g.add_argument("--stop-after", type=int, default=None,
                   help="run at most this many epochs now (continue later with --resume)")
    g.add_argument("--stop-after-steps", type=int, default=None,
                   help="run at most this many steps now, then checkpoint (continue later with --resume)")
    g.add_argument("--fit-minutes", type=float, default=None, metavar="M",
                   help="crop sampler: time --calibrate-steps steps, then choose --epochs (and, if fewer than 2 "
                        "fit, --steps-per-epoch) so the whole schedule ends within M minutes of this command "
                        "(train/budget.py); the choice is printed and recorded")
    g.add_argument("--calibrate-steps", type=int, default=20, help="steps timed by --fit-minutes")
    g.add_argument("--checkpoint-minutes", type=float, default=d.checkpoint_minutes,
                   help="also checkpoint within an epoch this often")
    g.add_argument("--seed", type=int, default=d.seed)
    g.add_argument("--threads", type=int, default=None, help="torch CPU threads (per process under torchrun)")
    g.add_argument("--device", default=None,
                   help="torch device (default: cuda if available, else cpu; under torchrun cuda means "
                        "cuda:LOCAL_RANK)")
    g.add_argument("--val-examples", type=int, default=d.val_examples)
    g.add_argument("--val-pixels", type=int, default=d.val_pixels)
    g.add_argument("--val-ndisp", type=int, default=None,
                   help="disparity range of the WTA validation (default: the pair's ndisp, 228 for KITTI)")
    g.add_argument("--no-progress", action="store_true")
    return p


def _git_commit() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                              cwd=Path(__file__).resolve().parent).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def main(argv=None) -> int:
    t0 = time.time()  # --fit-minutes counts from here
    args = build_parser().parse_args(argv)
    if args.threads:  # per process under torchrun
        torch.set_num_threads(args.threads)
        try:
            torch.set_num_interop_threads(1)
        except RuntimeError:
            pass
    device, created = init_distributed(args.device)  # torchrun: join the group, cuda:LOCAL_RANK
    try:
        return _main(args, argv, device, t0)
    finally:
        if created:
            dist.destroy_process_group()


def _fit_schedule(cfg, args, train_pairs, val_pairs, device, t0, world):
    """``--fit-minutes``: calibrate, then ``cfg`` with the epochs (and steps per epoch) that fit."""
    if args.resume is not None:
        raise InputError("--fit-minutes plans a new run: resume with the --epochs and --steps-per-epoch it chose")
    if world > 1:
        raise InputError("--fit-minutes times one process: give --epochs under torchrun")
    cal = calibrate(cfg, train_pairs, val_pairs, device, steps=args.calibrate_steps)
    left = 60.0 * args.fit_minutes - (time.time() - (t0 or time.time()))
    epochs, spe = plan(left, cal, cfg.steps_per_epoch, cfg.checkpoint_minutes)
    planned = cal.setup_s + epochs * (spe * cal.step_s + cal.epoch_end_s) + cal.export_s
    fit = {"minutes": args.fit_minutes, "seconds_left_at_plan": round(left, 1), "calibration": cal.as_dict(),
           "epochs": epochs, "steps_per_epoch": spe, "planned_s": round(planned, 1)}
    print(f"fit-minutes {args.fit_minutes:g}: {cal.step_s:.3f} s/step over {cal.steps} steps, epoch end "
          f"{cal.epoch_end_s:.1f} s, set-up {cal.setup_s:.1f} s; {left:.0f} s left -> --epochs {epochs} "
          f"--steps-per-epoch {spe} ({epochs * spe} steps, about {planned:.0f} s planned)", flush=True)
    return replace(cfg, epochs=epochs, steps_per_epoch=spe), fit


def _main(args, argv, device, t0=None) -> int:
    rank, world = _rank_world()
    commit = _git_commit()  # the code that trains, not whatever HEAD is when it ends
    ad = ARCH_DEFAULTS[args.arch]

    def pick(v, key):
        v = ad[key] if v is None else v
        return int(v) if isinstance(v, float) and v.is_integer() and key != "lr" else v
    cfg = TrainConfig(arch=args.arch, epochs=args.epochs, examples_per_epoch=args.examples_per_epoch,
                      batch_size=args.batch_size, lr=pick(args.lr, "lr"), lr_steps=tuple(args.lr_steps),
                      lr_factor=args.lr_factor, momentum=args.momentum, weight_decay=args.weight_decay,
                      n_lo=pick(args.n_lo, "n_lo"), n_hi=pick(args.n_hi, "n_hi"), p_hi=pick(args.p_hi, "p_hi"),
                      gt=args.gt, max_per_pair=args.max_per_pair, augment=args.augment,
                      augment_preset=args.augment_preset, balance=args.balance,
                      family_offsets=args.family_offsets,
                      conv_layers=[list(c) for c in pick(args.conv, "conv_layers")],
                      fc_layers=list(pick(args.fc, "fc_layers")), margin=args.margin, sampler=args.sampler,
                      crop=tuple(args.crop), spread=args.spread, per_crop=args.per_crop,
                      crops_per_step=args.crops_per_step, negatives=args.negatives, subpixel=args.subpixel,
                      steps_per_epoch=args.steps_per_epoch, checkpoint_minutes=args.checkpoint_minutes,
                      seed=args.seed, val_examples=args.val_examples, val_pixels=args.val_pixels,
                      val_ndisp=args.val_ndisp, progress=not args.no_progress)
    try:
        train_refs, held_refs = select_pairs(args.data, args.holdout, args.include, args.dataset)
        train_pairs = [r.load() for r in train_refs]
        no_gt = [p.key for p in train_pairs if p.disp is None]
        if no_gt:
            print(f"skipping {len(no_gt)} pair(s) without ground truth: {', '.join(no_gt)}", file=sys.stderr)
            train_pairs = [p for p in train_pairs if p.disp is not None]
        if not train_pairs:
            raise InputError("none of the training pairs has ground truth")
        val_pairs = [r.load() for r in held_refs]
        init = None
        if args.init is not None:
            from mccnn_cl.errors import WeightsError
            from mccnn_cl.models import resolve
            try:
                init = resolve(args.init)
            except WeightsError as exc:
                raise InputError(f"--init {args.init}: {exc}") from exc
        fit = None
        if args.fit_minutes is not None:
            cfg, fit = _fit_schedule(cfg, args, train_pairs, val_pairs, device, t0, world)
        result = train(cfg, train_pairs, val_pairs, device, args.out, resume=args.resume,
                       stop_after=args.stop_after, stop_after_steps=args.stop_after_steps, init=init)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if rank == 0:
        prov = result["provenance"]
        launcher = "python -m" if world == 1 else f"torchrun --nproc_per_node={world} -m"
        prov["command"] = f"{launcher} mccnn_cl.train.train " + " ".join(
            shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
        prov["git_commit"] = commit
        if init is not None:
            try:
                record_init(prov, init, args.init)
            except Exception as exc:  # noqa: BLE001 - a provenance problem must not lose the trained weights
                prov["init"] = {"weights": str(args.init), "licence": init.meta.get("licence"),
                                "provenance_error": f"{type(exc).__name__}: {exc}"}
                print(f"warning: the lineage of --init {args.init} could not be recorded ({type(exc).__name__}: "
                      f"{exc}); the weights are written without it", file=sys.stderr)
        if fit is not None:
            prov["fit_minutes"] = fit
        prov["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        prov = json.loads(json.dumps(prov, default=str))  # anything JSON cannot hold, as text: never a lost export
        export = args.export or str(Path(args.out) / "weights.npz")
        result["model"].cpu().to_weights({"training": prov}).save(export)
        print(f"exported {export}")
    if world > 1:
        dist.barrier()  # every rank ends once the export is written
    return 0


if __name__ == "__main__":
    sys.exit(main())
