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
a mid-epoch checkpoint.  A run locks its folder (``OUT/.lock``), refuses a
folder holding an earlier run unless ``--resume`` or ``--force``, writes every
file atomically, and on Ctrl-C or SIGTERM stops between steps with a
checkpoint (exit status 130 / 143; docs/training.md, "Running, stopping and
resuming safely").

Launched by torchrun (``WORLD_SIZE`` > 1) it trains with
DistributedDataParallel, one process per device (gloo on the CPU, NCCL on
CUDA ``cuda:LOCAL_RANK``): each step every rank takes its own share of one
draw (``--crops-per-step`` crops, or ``--batch-size`` patch pairs, per rank),
so the ranks together train on exactly the batch one process would get with
N times as many; only rank 0 validates, logs and writes files.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import fnmatch
import io
import json
import math
import os
import platform
import shlex
import signal
import subprocess
import sys
import tempfile
import threading
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
           "load_checkpoint", "TrainingInterrupted", "main"]


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


def available_devices() -> str:
    """The torch devices training can use here, for messages: ``cpu``, and ``cuda`` (with its
    indices) only where ``torch.cuda.is_available()``."""
    if not torch.cuda.is_available():
        return "cpu"
    n = torch.cuda.device_count()
    return f"cpu, cuda (cuda:0{f'..cuda:{n - 1}' if n > 1 else ''})"


def check_device(spec=None, world: int = 1) -> torch.device:
    """The torch device ``--device`` names (None: CUDA when available, else the CPU), checked
    before any work: a name torch does not know, a device type training does not run on, CUDA
    on a machine (or torch build) without it, or a CUDA index past the devices is an
    :class:`InputError` naming ``spec`` and what is available.  Under torchrun (``world`` > 1)
    the index is replaced by ``LOCAL_RANK`` (:func:`init_distributed`), checked there."""
    if spec is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(spec)
    except (RuntimeError, ValueError, TypeError):
        raise InputError(f"--device {spec}: not a torch device; available: {available_devices()}") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch build has no CUDA" if torch.version.cuda is None else "no CUDA device is usable"
            raise InputError(f"--device {spec}: CUDA is not available ({why}, torch {torch.__version__}); "
                             f"available: {available_devices()}")
        if world <= 1 and device.index is not None and device.index >= torch.cuda.device_count():
            raise InputError(f"--device {spec}: no such CUDA device; available: {available_devices()}")
    elif device.type != "cpu":
        raise InputError(f"--device {spec}: training runs on cpu or cuda; available: {available_devices()}")
    return device


def init_distributed(device=None):
    """Join the process group when launched by torchrun (``WORLD_SIZE`` > 1).

    Returns ``(device, created)``: the device this process trains on (on CUDA
    ``cuda:LOCAL_RANK``, whatever index ``device`` names; default CUDA when
    available, else the CPU) and whether this call created the process group
    (the caller then destroys it).  Backend: NCCL on CUDA, gloo on the CPU.
    Without torchrun (or with one process) nothing is initialised.  A device
    this machine lacks, a ``LOCAL_RANK`` past its CUDA devices, or a backend
    this torch build lacks is an :class:`InputError` before anything starts
    (:func:`check_device`).
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    device = check_device(device, world)
    if world <= 1:
        return device, False
    if not dist.is_available():
        raise InputError("WORLD_SIZE > 1 but this torch build has no torch.distributed")
    if device.type == "cuda":
        rank, n = int(os.environ.get("LOCAL_RANK", "0")), torch.cuda.device_count()
        if rank >= n:
            raise InputError(f"LOCAL_RANK {rank}: this machine has {n} CUDA device(s) (cuda:0..cuda:{n - 1}); "
                             f"start at most {n} processes per node (torchrun --nproc_per_node={n})")
        device = torch.device("cuda", rank)
        torch.cuda.set_device(device)
    backend = "nccl" if device.type == "cuda" else "gloo"
    if not getattr(dist, f"is_{backend}_available")():
        raise InputError(f"--device {device.type}: distributed training on {device.type} needs the {backend} "
                         "backend, which this torch build lacks")
    if dist.is_initialized():
        return device, False
    dist.init_process_group(backend, timeout=DIST_TIMEOUT)
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

def _say(*args, **kw) -> None:
    """``print`` flushed at once: a log redirected to a file (``nohup ... > log.txt``) is
    block-buffered, and a training run's lines must reach it as they are written."""
    print(*args, **kw, flush=True)


def _json_safe(obj):
    """``obj`` with every non-finite float (inf, NaN) as None: valid JSON for any reader
    (Python's ``json`` would write ``Infinity``/``NaN``, which other tools reject)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def _json_line(obj) -> str:
    return json.dumps(_json_safe(obj), allow_nan=False)


@contextlib.contextmanager
def _writing(path):
    """An OSError (disk full, folder gone, I/O error) while writing ``path`` as one
    InputError line naming it; the file written before stays whole (atomic writes)."""
    try:
        yield
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror or exc} (its previous version, if any, is "
                         "unchanged)") from exc


def _atomic_json(obj, path: Path) -> None:
    """``obj`` as indented, valid JSON at ``path`` (non-finite numbers as null), whole or not at all
    (:func:`mccnn_cl.atomic.atomic_write`: a temporary file of a unique name, then a rename)."""
    from ..atomic import atomic_write

    text = json.dumps(_json_safe(obj), indent=1, allow_nan=False)

    def write(tmp):
        with open(tmp, "w") as f:
            f.write(text)
    with _writing(path):
        atomic_write(path, write)


def _atomic_torch_save(obj, path: Path):
    """``torch.save(obj)`` at ``path``, whole or not at all (a temporary file of a unique name, so two
    writers never write into one temporary file; see :mod:`mccnn_cl.atomic`)."""
    from ..atomic import atomic_write_bytes

    with _writing(path):
        buf = io.BytesIO()
        torch.save(obj, buf)
        atomic_write_bytes(path, buf.getvalue())


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
    from ..atomic import atomic_write
    try:
        with _writing(path):
            atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=100))  # tmp keeps .png: the format
    finally:
        plt.close(fig)


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
    """Write the weights .npz atomically (a reader never sees half a file; a temporary file of a
    unique name: :meth:`mccnn_cl.weights.Weights.save`)."""
    w = copy.deepcopy(model).cpu().to_weights(meta)  # a copy: the trained (maybe DDP-held) net stays put
    with _writing(path):
        w.save(path)


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


# -- run folder, checkpoints, interruption ----------------------------------------

#: The lock file a run holds (``flock``) in its folder while it trains (rank 0 under torchrun).
LOCK_NAME = ".lock"
#: The files a run writes into its folder (``--force`` removes an earlier run's before starting).
RUN_FILES = ("checkpoint.pt", "run.json", "history.json", "training.png", "latest.npz", "best.npz")
#: Files whose presence marks a folder as holding a run.
RUN_MARKERS = ("checkpoint.pt", "run.json", "history.json")


def run_lock(out_dir):
    """The run folder's lock (:class:`mccnn_cl.atomic.exclusive_lock` on ``OUT/.lock``): a second
    run on the same folder is refused, naming the process that holds it."""
    from ..atomic import exclusive_lock
    return exclusive_lock(Path(out_dir) / LOCK_NAME,
                          busy=f"another training run is using {out_dir} ({{holder}}; lock file {{path}}): "
                               "wait for it to end, or give another --out")


def prepare_run_folder(out_dir) -> Path:
    """Create ``out_dir`` (with its parents) and check that files can be written into it: one
    InputError line naming the folder otherwise (not a traceback at the first checkpoint)."""
    from ..atomic import check_writable
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir} is a file, not a folder")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the run folder {out_dir}: {exc.strerror or exc}") from exc
    check_writable(out_dir)
    return out_dir


def _weights_hint(folder: Path, given: Path | None = None) -> str:
    ck = folder / "checkpoint.pt"
    if given is not None and ck.is_file() and not _same_file(ck, given):
        return f"the run's own checkpoint is {ck}"
    have = [n for n in ("latest.npz", "best.npz") if (folder / n).is_file()]
    if not have:
        return "resume from a copy of an earlier checkpoint.pt if you have one, or start a new run"
    return (f"resume from a copy of an earlier checkpoint.pt if you have one; {' and '.join(have)} in {folder} "
            f"{'hold' if len(have) > 1 else 'holds'} weights only (no optimizer state, no position in the "
            f"schedule) and cannot be resumed: to keep that training, start a new run from them with --init "
            f"{folder / have[0]} and another --out (a new schedule, not the interrupted run's result)")


def load_checkpoint(path, map_location="cpu") -> dict:
    """Read a run's ``checkpoint.pt`` for ``--resume``; a missing, unreadable or damaged file
    (or a weights .npz given instead) is one InputError line naming it and what can be done."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"--resume {path}: no such file; {_weights_hint(p.parent, p)}"
                         if p.parent.is_dir() else f"--resume {path}: no such file (nor its folder)")
    if p.is_dir():
        hint = f" (its checkpoint: --resume {p / 'checkpoint.pt'})" if (p / "checkpoint.pt").is_file() else ""
        raise InputError(f"--resume {path} is a folder, not a checkpoint file{hint}")
    if p.suffix == ".npz":
        raise InputError(f"--resume {path} is a weights file, not a checkpoint: it holds no optimizer state or "
                         f"position in the schedule; resume with the run's checkpoint.pt, or start a new run from "
                         f"these weights with --init {path}")
    try:
        with open(p, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise InputError(f"--resume {path}: cannot read it ({exc.strerror or exc})") from exc
    try:  # read first, parsed apart: torch reports a truncated archive as an OSError too
        ck = torch.load(io.BytesIO(data), map_location=map_location, weights_only=False)
    except Exception as exc:  # noqa: BLE001 - truncated zip, bad pickle, ...: all mean a damaged file
        why = str(exc).strip().splitlines()[0][:120] if str(exc).strip() else type(exc).__name__
        raise InputError(f"--resume {path}: the checkpoint is damaged (truncated or overwritten; {why}); "
                         f"{_weights_hint(p.parent, p)}") from exc
    need = ("model", "optimizer", "config", "history", "epoch")
    if not isinstance(ck, dict) or any(k not in ck for k in need):
        raise InputError(f"--resume {path}: not a training checkpoint of this package (expected the keys "
                         f"{', '.join(need)}); {_weights_hint(p.parent)}")
    return ck


def check_resumable(ck: dict, cfg: TrainConfig, world: int, resume) -> None:
    """InputError when checkpoint ``ck`` cannot continue as ``cfg`` with ``world`` processes."""
    c = ck["config"]
    if (c["conv_layers"] != cfg.conv_layers or c["fc_layers"] != cfg.fc_layers
            or c.get("arch", "paper") != cfg.arch):
        raise InputError(f"{resume}: checkpoint has another architecture")
    if ck.get("mid") is not None and ck.get("world_size", 1) != world:
        raise InputError(f"{resume}: a mid-epoch checkpoint of a run with {ck.get('world_size', 1)} "
                         f"process(es): resume it with as many (here {world}), or from an epoch's end")


class TrainingInterrupted(KeyboardInterrupt):
    """Raised by :func:`train` after a SIGINT (Ctrl-C) or SIGTERM, once the checkpoint is written
    (between steps: the mid-epoch checkpoint; at an epoch's end: that epoch's).  ``code``: the exit
    status the command line returns (128 + the signal: 130, 143)."""

    def __init__(self, signum: int, epoch: int, step: int, steps: int, checkpoint: Path):
        self.signum, self.epoch, self.step, self.steps, self.checkpoint = signum, epoch, step, steps, checkpoint
        self.code = 128 + signum
        super().__init__(self.line())

    def line(self) -> str:
        return (f"interrupted ({signal.Signals(self.signum).name}) at epoch {self.epoch} step "
                f"{self.step}/{self.steps}; saved {self.checkpoint}; resume with --resume {self.checkpoint} "
                "(and the same options)")


class _Stopped(KeyboardInterrupt):
    """A signal that stops at once: SIGTERM outside the training loop (loading data, exporting),
    or a second SIGINT/SIGTERM within it."""

    def __init__(self, signum):
        super().__init__(signum)
        self.signum = signum


class _SignalFlag:
    """While entered (main thread only): SIGINT and SIGTERM set ``signum`` instead of stopping the
    process, so the loop can stop between steps with a checkpoint; a second signal stops it at
    once (KeyboardInterrupt).  The previous handlers come back on exit."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.signum = None
        self._prev = {}

    def _handle(self, signum, frame):
        if self.signum is not None:
            raise _Stopped(signum)
        self.signum = signum

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                self._prev[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc):
        for s, h in self._prev.items():
            signal.signal(s, h)
        self._prev = {}
        return False


def _merge_parts(parts: list) -> list:
    """Consecutive parts of a run with the same pairs and process count as one."""
    out = []
    for p in parts:
        q = out[-1] if out else None
        if q is not None and all(q.get(k) == p.get(k) for k in ("trained_on", "held_out", "processes")):
            q["steps"] = [q["steps"][0], p["steps"][1]]
        else:
            out.append(dict(p))
    return out


def pairs_of_parts(parts: list, held_now: list) -> tuple:
    """(trained_on, held_out) of a run made of ``parts``: every pair any part trained on (pair key ->
    GT locations, the latest part's count), and the pairs held out by a part (``held_now`` last)
    that no part trained on."""
    trained = {}
    for p in parts:
        trained.update(p.get("trained_on") or {})
    held = []
    for k in [k for p in parts for k in (p.get("held_out") or [])] + list(held_now):
        if k not in trained and k not in held:
            held.append(k)
    return trained, held


def _data_changes(before: dict, trained: dict, held: list) -> list:
    """The differences in pairs between a checkpoint's last part ``before`` and this run."""
    if before.get("trained_on") is None:
        return ["pairs unknown (a checkpoint of an older version records none)"]
    out = []
    for name, old, new in (("training pairs", set(before["trained_on"]), set(trained)),
                           ("held-out pairs", set(before.get("held_out") or []), set(held))):
        if old != new:
            out.append(f"{name} " + " ".join([f"+{k}" for k in sorted(new - old)]
                                             + [f"-{k}" for k in sorted(old - new)]))
    return out


def train(cfg: TrainConfig, train_pairs, val_pairs, device, out_dir, resume=None, log=_say,
          stop_after: int | None = None, stop_after_steps: int | None = None, init=None,
          resume_state: dict | None = None) -> dict:
    """Train on ``train_pairs`` (StereoPairs with GT), validate on ``val_pairs`` each epoch.

    Writes ``checkpoint.pt`` (every epoch and every ``cfg.checkpoint_minutes``
    within one), ``history.json``, ``run.json`` (progress: step, examples,
    wall time, ETA), ``training.png``, ``latest.npz`` (weights after each epoch)
    and ``best.npz`` (whenever the validation WTA error improves) in
    ``out_dir``, each atomically (a temporary file of a unique name, then a
    rename), ``checkpoint.pt`` first at an epoch's end; an OSError while
    writing (disk full) is an InputError naming the file.  ``out_dir`` is
    locked (``OUT/.lock``, :func:`run_lock`) while the run trains: a second
    run on it is refused.  ``resume``: a checkpoint path to continue from (bit
    for bit, also from a mid-epoch checkpoint; ``resume_state``: that file
    already read by :func:`load_checkpoint`).  ``stop_after``: run at most this many
    epochs in this call; ``stop_after_steps``: stop (with a checkpoint) after
    this many steps in this call (the schedule still spans ``cfg.epochs``).
    ``init``: a :class:`~mccnn_cl.weights.Weights` of ``cfg``'s layers to start
    from instead of He initialisation (fine-tuning; :mod:`.selftrain`).
    Returns ``{"model": MCCNN (on device), "history": [...], "provenance": {...}}``.

    SIGINT (Ctrl-C) or SIGTERM (called from the main thread) stops the run
    after the current step: the mid-epoch checkpoint is written (at an
    epoch's last step, the epoch's end first) and :class:`TrainingInterrupted`
    is raised; ``--resume`` then continues bit for bit.  A second signal
    stops at once (KeyboardInterrupt; the last checkpoint stays whole).

    The checkpoint records every part of the run (each call that trained:
    its steps, process count, training and held-out pair keys); the
    provenance's ``trained_on`` is every pair of every part and its
    ``held_out`` never names a pair some part trained on.  A resume with
    other pairs or another process count is allowed, with a warning.

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
    validates, logs and writes files (and holds the lock); the others wait at
    a barrier after each epoch.  All ranks load ``resume``; a signal is agreed
    on by all ranks at the next step (an all-reduce each step already runs).
    """
    if cfg.arch not in ARCHS:
        raise InputError(f"unknown architecture {cfg.arch!r} (expected one of {', '.join(ARCHS)})")
    if cfg.sampler not in ("patch", "crop"):
        raise InputError(f"sampler must be 'patch' or 'crop', got {cfg.sampler!r}")
    if cfg.sampler == "patch" and (cfg.batch_size < 2 or cfg.batch_size % 2):
        raise InputError(f"batch size must be even (half positive, half negative), got {cfg.batch_size}")
    rank, _ = _rank_world()
    out_dir = Path(out_dir)
    with contextlib.ExitStack() as stack:
        if rank == 0:
            prepare_run_folder(out_dir)
            stack.enter_context(run_lock(out_dir))
        flag = stack.enter_context(_SignalFlag())
        return _train(cfg, train_pairs, val_pairs, device, out_dir, resume, log, stop_after, stop_after_steps,
                      init, resume_state, flag)


def _train(cfg, train_pairs, val_pairs, device, out_dir, resume, log, stop_after, stop_after_steps, init,
           resume_state, flag) -> dict:
    device = torch.device(device)
    rank, world = _rank_world()
    lead = rank == 0
    if not lead:
        log = lambda *a, **k: None  # noqa: E731
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
    trained_now = {k: int(v) for k, v in sampler.counts().items()}
    held_now = vset.keys if lead else [p.key for p in val_pairs]
    history, start_epoch, start_i, elapsed0, examples0 = [], 0, 0, 0.0, 0
    mid = None
    best = float("inf")
    parts_before = []
    if resume is not None:
        ck = resume_state if resume_state is not None else load_checkpoint(resume)
        check_resumable(ck, cfg, world, resume)
        c = ck["config"]
        ck_world = ck.get("world_size", 1)
        parts_before = ck.get("parts") or [{"steps": [0, None], "processes": ck_world, "trained_on": None,
                                            "held_out": None}]  # an older version's: pairs not recorded
        changed = [d for d in [resume_changes(c, cfg)] if d]
        if ck_world != world:
            changed.append(f"processes {ck_world} -> {world} (the batch of a step changes with them)")
        changed += _data_changes(parts_before[-1], trained_now, held_now)
        if changed:  # allowed (e.g. a shorter schedule when the machine slows), never silent
            log(f"warning: resuming {resume} with settings the run did not start with ({'; '.join(changed)}): "
                "the result is not the one an uninterrupted run would give; the provenance records each part")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        history, elapsed0 = ck["history"], ck.get("elapsed", 0.0)
        examples0 = ck.get("examples_seen", sum(h["examples"] for h in history))
        best = ck.get("best_err3")
        best = float("inf") if best is None else float(best)
        mid = ck.get("mid")
        if mid is not None:
            start_epoch, start_i = mid["epoch"], mid["i"]
            log(f"resumed from {resume} in epoch {start_epoch + 1}, step {start_i}")
        else:
            start_epoch = ck["epoch"] + 1
            log(f"resumed from {resume} after epoch {ck['epoch'] + 1}")
    start_step = start_epoch * iters_per_epoch + start_i
    if parts_before and parts_before[-1]["steps"][1] is None:
        parts_before[-1]["steps"][1] = start_step
    part = {"steps": [start_step, start_step], "processes": world, "trained_on": trained_now,
            "held_out": list(held_now)}

    def parts():
        """Every part of the run so far (this one once it has trained a step, or when it is the first)."""
        now = [part] if part["steps"][1] > part["steps"][0] or not parts_before else []
        return _merge_parts(copy.deepcopy(parts_before) + copy.deepcopy(now))

    def run_pairs():
        return pairs_of_parts(parts(), held_now)

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

    def eta_s(step):
        """Seconds to the end of the schedule at this call's pace so far (epoch ends included)."""
        done = step - start_step
        if done <= 0:
            return None
        return round((time.time() - t_start) / done * max(total_iters - step, 0), 1)

    def progress(step_epoch, step_i):
        step = step_epoch * iters_per_epoch + step_i
        return {"arch": cfg.arch, "sampler": cfg.sampler, "epoch": step_epoch, "step": step,
                "total_steps": total_iters, "examples_seen": int(examples_seen),
                "wall_time_s": round(elapsed0 + time.time() - t_start, 1), "eta_s": eta_s(step),
                "best_val_err3": best if math.isfinite(best) else None,
                "updated_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                **({"processes": world} if world > 1 else {})}

    def save_ck(epoch, mid_state):
        step_epoch, step_i = (mid_state["epoch"], mid_state["i"]) if mid_state else (epoch + 1, 0)
        part["steps"][1] = step_epoch * iters_per_epoch + step_i
        _atomic_torch_save({"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch,
                            "history": history, "config": asdict(cfg), "elapsed": elapsed0 + time.time() - t_start,
                            "examples_seen": examples_seen, "best_err3": best, "mid": mid_state,
                            "world_size": world, "parts": parts()},
                           out_dir / "checkpoint.pt")
        _atomic_json(progress(step_epoch, step_i), out_dir / "run.json")

    def interrupted(signum, epoch_1, step, steps):
        return TrainingInterrupted(signum, epoch_1, step, steps, out_dir / "checkpoint.pt")

    end_epoch = cfg.epochs if stop_after is None else min(cfg.epochs, start_epoch + stop_after)
    stopped = False
    stop_signal = None     # the signal all ranks agreed to stop on (world 1: this process's)
    stop_at = None         # (epoch 1-based, step, steps) where it stopped
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
                # mean loss (the crop loss averages over a count proportional to n_ex).  The last two
                # entries: the sum of the signal numbers the ranks have received and how many have one,
                # so that all ranks stop after the same step (in the same all-reduce: no extra one).
                sig = flag.signum or 0
                tot = torch.tensor([float(n_ex), float(loss.detach()) * n_ex, float(sig), float(sig > 0)],
                                   dtype=torch.float64, device=device)
                dist.all_reduce(tot)
                n_tot, loss_tot, sig_sum, n_sig = tot.tolist()
                if n_sig > 0 and stop_signal is None:
                    s_avg = sig_sum / n_sig  # ranks with different signals: SIGTERM
                    stop_signal = int(s_avg) if s_avg in (signal.SIGINT, signal.SIGTERM) else int(signal.SIGTERM)
                loss = loss * (world * n_ex / n_tot)
                step_loss, n_step = loss_tot / n_tot, int(round(n_tot))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            loss_sum += (float(loss.detach()) if step_loss is None else step_loss) * n_step
            seen += n_step
            seen_here += n_step
            examples_seen += n_step
            part["steps"][1] = it + 1
            if world == 1 and flag.signum is not None:
                stop_signal = flag.signum
            if bar is not None:
                bar.update(1)
                if i % 50 == 0:
                    bar.set_postfix(loss=f"{loss_sum / seen:.4f}", ex_s=f"{seen_here / (time.time() - t_here):.0f}",
                                    lr=f"{lr:g}")
            last = i + 1 == n_it
            if steps_left is not None:
                steps_left -= 1
            stop_now = not last and (steps_left == 0 or stop_signal is not None)
            if lead and not last and (time.time() - last_ck > 60 * cfg.checkpoint_minutes or stop_now):
                save_ck(epoch - 1, {"epoch": epoch, "i": i + 1, "loss_sum": loss_sum, "seen": seen,
                                    "gen": gen.get_state()})
                last_ck = time.time()
                log(_json_line({"checkpoint": progress(epoch, i + 1),
                                "train_loss_so_far": round(loss_sum / max(seen, 1), 5)}))
            if stop_now:
                stopped = True
                if stop_signal is not None:
                    stop_at = (epoch + 1, i + 1, n_it)
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
            # checkpoint.pt first: the file a resume needs, whatever happens to the others
            save_ck(epoch, None)
            last_ck = time.time()
            trained, held = run_pairs()
            snap = {"training": {"arch": cfg.arch, "epoch": epoch + 1, "examples_seen": int(examples_seen),
                                 "wall_time_s": rec["wall_time_s"], "held_out": held, "trained_on": trained,
                                 "validation": {k: v for k, v in rec.items() if k.startswith("val_")},
                                 "config": {k: v for k, v in asdict(cfg).items() if k != "progress"}}}
            _export(model, out_dir / "latest.npz", snap)
            if improved:
                _export(model, out_dir / "best.npz", snap)
            _atomic_json(history, out_dir / "history.json")
            plot_history(history, out_dir / "training.png",
                         title=f"MC-CNN-{cfg.arch} training ({cfg.sampler} sampler)",
                         loss_name={"paper": "cross-entropy", "fst": "hinge loss",
                                    "acrt": "binary cross-entropy"}[cfg.arch])
            line = {k: (round(v, 5) if isinstance(v, float) else v) for k, v in rec.items()}
            line["eta_s"] = eta_s((epoch + 1) * iters_per_epoch)
            log(_json_line(line))
        if world > 1:
            dist.barrier()
        if world == 1 and flag.signum is not None:  # a signal during the epoch's end (validation, files)
            stop_signal = flag.signum
        if stop_signal is not None and epoch + 1 < cfg.epochs:
            stop_at = (epoch + 1, n_it, n_it)
            break
        if steps_left == 0:
            break
    if world > 1:
        dist.barrier()  # rank 0's files (also a mid-epoch checkpoint at a stop) are written when train returns
    if stop_at is not None:
        raise interrupted(stop_signal, *stop_at)
    elapsed = elapsed0 + (time.time() - t_start)
    trained, held = run_pairs()
    prov = {
        "architecture": ARCHS[cfg.arch],
        "trained_on": trained,
        "held_out": held,
        "epochs": cfg.epochs,
        "epochs_done": len(history),
        "examples": int(examples_seen),
        "iterations": total_iters,
        **({"processes": world, "batch_per_step": (f"{world} x {cfg.crops_per_step} crops" if cfg.sampler == "crop"
                                                  else f"{world} x {cfg.batch_size} examples")}
           if world > 1 else {}),
        "parts": [{"steps": p["steps"], "processes": p["processes"],
                   "trained_on": None if p.get("trained_on") is None else sorted(p["trained_on"]),
                   "held_out": p.get("held_out")} for p in parts()],
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
    g.add_argument("--force", action="store_true",
                   help="start a new run in a folder that holds an earlier one (its run files are removed; "
                        "without --force such a run is refused), or over an existing --export file")
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
                   help="torch device: cpu, or cuda[:N] where torch.cuda.is_available() (default: cuda if "
                        "available, else cpu; under torchrun cuda means cuda:LOCAL_RANK); another is refused")
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


@contextlib.contextmanager
def _term_stops():
    """While open (main thread only): SIGTERM raises :class:`_Stopped` (as SIGINT raises
    KeyboardInterrupt), so that the command ends with one line, not a silent kill; the training
    loop replaces both with a checkpoint-then-stop (:class:`_SignalFlag`)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        raise _Stopped(signum)
    prev = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, prev)


def _line_buffered() -> None:
    """stdout line-buffered even when it is not a terminal (``nohup ... > log.txt``): each log
    line reaches the file when it is written, not in blocks of several kB."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.reconfigure(line_buffering=True)
        except (AttributeError, ValueError, io.UnsupportedOperation):  # not a TextIOWrapper (captured)
            pass


def main(argv=None) -> int:
    t0 = time.time()  # --fit-minutes counts from here
    _line_buffered()
    args = build_parser().parse_args(argv)
    if args.threads:  # per process under torchrun
        torch.set_num_threads(args.threads)
        try:
            torch.set_num_interop_threads(1)
        except RuntimeError:
            pass
    try:
        device, created = init_distributed(args.device)  # torchrun: join the group, cuda:LOCAL_RANK
    except InputError as exc:  # a device or backend this machine lacks: one line, before any work
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        with _term_stops():
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


def _agree(err: str | None, world: int) -> None:
    """Raise InputError(``err``) on every rank when any rank has one (under torchrun the ranks must
    stop together: one that went on would wait for the others at the first collective)."""
    if world > 1:
        errs = [None] * world
        dist.all_gather_object(errs, err)
        err = next((e for e in errs if e), None)
    if err:
        raise InputError(err)


def _same_file(a, b) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(a) == os.path.abspath(b)


def _prepare_out(args, out: Path, export: Path, stack) -> None:
    """Rank 0, before any data is read: the run folder exists and is writable, the export's folder
    too, and the folder is locked for this run.  InputError (one line) otherwise."""
    prepare_run_folder(out)
    from ..atomic import check_writable
    if args.export is not None:
        if export.is_dir():
            raise InputError(f"--export {export} is a folder: give a file name (.npz)")
        check_writable(export.parent if str(export.parent) else Path("."))
    stack.enter_context(run_lock(out))


def _earlier_run(args, out: Path, export: Path) -> list:
    """The files of an earlier run in ``out`` (and an existing export) that a new run would
    overwrite: refused unless --force (then returned, to be removed); [] when continuing it."""
    if args.resume is not None and _same_file(args.resume, out / "checkpoint.pt"):
        return []
    earlier = [out / n for n in RUN_FILES if (out / n).exists()]
    marked = [p for p in earlier if p.name in RUN_MARKERS]
    if export.exists():
        earlier.append(export)
    if not (marked or export.exists()) or args.force:
        return earlier
    what = f"{out} holds an earlier run ({', '.join(p.name for p in marked)})" if marked else f"{export} exists"
    how = (f"continue it with --resume {out / 'checkpoint.pt'}, " if (out / "checkpoint.pt").exists() else "")
    raise InputError(f"{what}: {how}pass --force to start a new run over it (its files are removed), "
                     "or give another --out" + (" / --export" if args.export else ""))


def _main(args, argv, device, t0=None) -> int:
    rank, world = _rank_world()
    lead = rank == 0
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
    out = Path(args.out)
    export = Path(args.export) if args.export else out / "weights.npz"
    try:
        with contextlib.ExitStack() as stack:
            # Before any data is read: the folder, its lock, an earlier run there, the checkpoint.
            err, ck, earlier = None, None, []
            try:
                if lead:
                    _prepare_out(args, out, export, stack)
                if args.resume is not None:
                    ck = load_checkpoint(args.resume)
                    check_resumable(ck, cfg, world, args.resume)
                if lead:
                    earlier = _earlier_run(args, out, export)
            except InputError as exc:
                err = str(exc)
            _agree(err, world)
            if earlier:  # --force over an earlier run
                for p in earlier:
                    with _writing(p):
                        p.unlink()
                _say(f"--force: removed the earlier run's {', '.join(p.name for p in earlier)} in "
                     f"{os.path.commonpath([str(p.parent) for p in earlier])}")
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
            result = train(cfg, train_pairs, val_pairs, device, out, resume=args.resume,
                           stop_after=args.stop_after, stop_after_steps=args.stop_after_steps, init=init,
                           resume_state=ck)
            if lead:
                _export_run(result, args, argv, world, commit, init, fit, export)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except TrainingInterrupted as exc:
        if lead:
            print(exc.line(), file=sys.stderr)
        return exc.code
    except KeyboardInterrupt as exc:  # before the first step, or a second signal
        signum = getattr(exc, "signum", signal.SIGINT)
        if lead:
            ckp = out / "checkpoint.pt"
            where = (f"the last checkpoint is {ckp}: resume with --resume {ckp}" if ckp.is_file()
                     else "nothing was saved")
            print(f"interrupted ({signal.Signals(signum).name}); {where}", file=sys.stderr)
        return 128 + signum
    if world > 1:
        dist.barrier()  # every rank ends once the export is written
    return 0


def _export_run(result, args, argv, world, commit, init, fit, export: Path) -> None:
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
        if prov.get("init"):  # a pair the start was trained on is not held out either
            prov["held_out"] = [k for k in prov.get("held_out", []) if k not in pairs_of(prov.get("trained_on"))]
    if fit is not None:
        prov["fit_minutes"] = fit
    prov["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    # anything JSON cannot hold, as text (non-finite numbers as null): never a lost export
    prov = _json_safe(json.loads(json.dumps(prov, default=str)))
    w = result["model"].cpu().to_weights({"training": prov})
    with _writing(export):
        w.save(export)
    _say(f"exported {export}")


if __name__ == "__main__":
    from ..cli import run_entry_point  # a reader of stdout gone: exit 141, quietly

    raise SystemExit(run_entry_point(main))
