"""Train the MC-CNN network (paper, "Details of learning") and export it for the OpenCL side.

Run as ``python -m mccnn_cl.train.train --data DIR [DIR ...] --holdout KEY ... --out runs/NAME``.

Defaults are the paper's recipe: cross-entropy on the 2-way softmax (class 0 =
bad match, class 1 = good match), SGD, batch 128 (64 positive + 64 negative
pairs), learning rate 0.01 divided by 10 at 12/16 and 15/16 of the run, 16
epochs, shuffled examples, N_lo 4, N_hi 8, P_hi 1, per-image mean/std
normalisation.  The paper does not state a momentum; the default 0.9 is the
released code's (``--momentum 0`` for plain SGD).  The weights are He
initialised (see :meth:`MCCNN.he_init_`).

An "epoch" is ``--examples-per-epoch`` patch pairs (default: one positive
and one negative for every usable GT pixel of the training pairs, after the
``--max-per-pair`` cap), drawn afresh each epoch with offsets redrawn, so a
short run can still follow the paper's 16-epoch schedule on a fraction of
the data.  Each epoch ends with a checkpoint (``checkpoint.pt``: unwrapped
``state_dict``, optimizer, epoch, history), validation on the held-out pairs
(patch loss and WTA 3-px error, :mod:`.evaluate`) and an updated plot
(``training.png``).  The run is deterministic for a given ``--seed`` (and
thread count), and ``--resume`` continues it bit for bit.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from mccnn_cl.datasets import discover
from mccnn_cl.errors import InputError
from mccnn_cl.weights import PAPER_CONV, PAPER_FC

from .evaluate import make_validation, validate
from .model import MCCNN
from .patches import PatchSampler

__all__ = ["TrainConfig", "train", "select_pairs", "lr_at", "augment_batch", "main"]


@dataclass
class TrainConfig:
    """Every knob of a run (the CLI flags map one to one; see ``--help``)."""

    epochs: int = 16
    examples_per_epoch: int | None = None   # patch pairs (pos + neg); None: all GT pixels x2
    batch_size: int = 128                   # pos + neg; must be even
    lr: float = 0.01
    lr_steps: tuple = (12 / 16, 15 / 16)    # fractions of the run where lr is multiplied by lr_factor
    lr_factor: float = 0.1
    momentum: float = 0.9
    weight_decay: float = 0.0
    n_lo: int = 4
    n_hi: int = 8
    p_hi: int = 1
    gt: str = "all"                         # GT pixels making examples: "all" or "noc"
    max_per_pair: int | None = None         # cap on locations drawn from one pair per epoch
    augment: bool = False
    conv_layers: list = field(default_factory=lambda: [list(c) for c in PAPER_CONV])
    fc_layers: list = field(default_factory=lambda: list(PAPER_FC))
    seed: int = 0
    val_examples: int = 4000
    val_pixels: int = 3000
    val_ndisp: int | None = None            # D for the WTA error; None: pair's ndisp or 228 (KITTI)
    progress: bool = True


def lr_at(cfg: TrainConfig, it: int, total: int) -> float:
    """Learning rate at iteration ``it`` of ``total``: ``lr * lr_factor ** (#steps passed)``."""
    passed = sum(1 for s in cfg.lr_steps if it >= round(s * total))
    return cfg.lr * cfg.lr_factor ** passed


# -- augmentation (optional; from the released code, see NOTES.md) ---------------

def augment_batch(left: torch.Tensor, right: torch.Tensor, gen: torch.Generator,
                  rotate: float = 7.0, scale: float = 0.9, shear: float = 0.1,
                  brightness: float = 0.7, contrast: float = 1.3, right_brightness: float = 0.3):
    """Random geometric and photometric jitter of patch pairs (N, 1, P, P), in torch.

    Per pair one affine map (rotation up to ``rotate`` degrees, horizontal
    scale in [scale, 1], horizontal shear up to ``shear``) about the patch
    centre, applied to both patches (bilinear, border replicated; patches are
    the network's own 9x9, so corners sample the nearest edge), brightness
    ``+U(-b, b)`` and contrast ``*exp(U(-log c, log c))`` on the normalised
    intensities, and an extra ``U(-rb, rb)`` brightness on the right patch.
    The released code's ranges (NOTES.md) applied to normalised patches.
    """
    n = left.shape[0]
    dev = left.device

    def u(lo, hi):
        return torch.rand(n, generator=gen).to(dev) * (hi - lo) + lo
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
        refs.extend(discover(root, dataset))
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


# -- the loop ------------------------------------------------------------------

def _atomic_torch_save(obj, path: Path):
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def plot_history(history: list, path) -> None:
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
    ax.set_ylabel("cross-entropy")
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
    ax.set_title("MC-CNN training")
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


def train(cfg: TrainConfig, train_pairs, val_pairs, device, out_dir, resume=None, log=print,
          stop_after: int | None = None) -> dict:
    """Train on ``train_pairs`` (StereoPairs with GT), validate on ``val_pairs`` each epoch.

    Writes ``checkpoint.pt``, ``history.json`` and ``training.png`` in
    ``out_dir``.  ``resume``: a checkpoint path to continue from.
    ``stop_after``: run at most this many epochs in this call (the schedule
    still spans ``cfg.epochs``; continue later with ``resume``).  Returns
    ``{"model": MCCNN (on device), "history": [...], "provenance": {...}}``.
    """
    if cfg.batch_size < 2 or cfg.batch_size % 2:
        raise InputError(f"batch size must be even (half positive, half negative), got {cfg.batch_size}")
    device = torch.device(device)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    model = MCCNN(cfg.conv_layers, cfg.fc_layers).he_init_().to(device)
    opt = torch.optim.SGD(model.parameters(), lr=cfg.lr, momentum=cfg.momentum,
                          weight_decay=cfg.weight_decay)
    sampler = PatchSampler(train_pairs, patch_size=model.patch_size, n_lo=cfg.n_lo, n_hi=cfg.n_hi,
                           p_hi=cfg.p_hi, use=cfg.gt, max_per_pair=cfg.max_per_pair)
    vset = make_validation(val_pairs, model.patch_size, n_examples=cfg.val_examples,
                           n_pixels=cfg.val_pixels, seed=cfg.seed + 1, n_lo=cfg.n_lo, n_hi=cfg.n_hi,
                           p_hi=cfg.p_hi, ndisp=cfg.val_ndisp)
    per_epoch_locs = sum(sampler.locations_per_epoch().values())
    locs = per_epoch_locs if cfg.examples_per_epoch is None else cfg.examples_per_epoch // 2
    half = cfg.batch_size // 2
    iters_per_epoch = max(1, locs // half)
    total_iters = cfg.epochs * iters_per_epoch
    history, start_epoch, elapsed0 = [], 0, 0.0
    if resume is not None:
        ck = torch.load(resume, map_location=device, weights_only=False)
        if ck["config"]["conv_layers"] != cfg.conv_layers or ck["config"]["fc_layers"] != cfg.fc_layers:
            raise InputError(f"{resume}: checkpoint has another architecture")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        start_epoch, history, elapsed0 = ck["epoch"] + 1, ck["history"], ck.get("elapsed", 0.0)
        log(f"resumed from {resume} after epoch {ck['epoch'] + 1}")
    log(f"training on {len(train_pairs)} pairs ({', '.join(sampler.keys)}), "
        f"{per_epoch_locs} locations per full epoch; validating on {', '.join(vset.keys) or 'nothing'}")
    log(f"{cfg.epochs} epochs x {iters_per_epoch} iterations x {cfg.batch_size} examples "
        f"= {total_iters * cfg.batch_size} examples; device {device}")
    t_start = time.time()
    end_epoch = cfg.epochs if stop_after is None else min(cfg.epochs, start_epoch + stop_after)
    for epoch in range(start_epoch, end_epoch):
        rng = np.random.default_rng([cfg.seed, epoch])
        gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
        plan = sampler.epoch(rng, n_locations=iters_per_epoch * half)
        n_it = min(iters_per_epoch, len(plan[0]) // half)
        model.train()
        loss_sum, seen, t0 = 0.0, 0, time.time()
        bar = None
        if cfg.progress:
            from tqdm import tqdm
            bar = tqdm(total=n_it, desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="it",
                       mininterval=1.0 if sys.stderr.isatty() else 30.0, leave=False)
        for i in range(n_it):
            it = epoch * iters_per_epoch + i
            lr = lr_at(cfg, it, total_iters)
            for g in opt.param_groups:
                g["lr"] = lr
            b = sampler.batch(plan, i * half, (i + 1) * half)
            left = torch.from_numpy(b.left).to(device)
            right = torch.from_numpy(b.right).to(device)
            labels = torch.from_numpy(b.labels).to(device)
            if cfg.augment:
                left, right = augment_batch(left, right, gen)
            loss = F.cross_entropy(model(left, right), labels)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            loss_sum += float(loss.detach()) * len(labels)
            seen += len(labels)
            if bar is not None:
                bar.update(1)
                if i % 50 == 0:
                    bar.set_postfix(loss=f"{loss_sum / seen:.4f}", ex_s=f"{seen / (time.time() - t0):.0f}",
                                    lr=f"{lr:g}")
        if bar is not None:
            bar.close()
        train_time = time.time() - t0
        rec = {"epoch": epoch + 1, "train_loss": loss_sum / max(seen, 1), "examples": seen,
               "lr": lr_at(cfg, epoch * iters_per_epoch + max(n_it - 1, 0), total_iters),
               "examples_per_s": seen / max(train_time, 1e-9)}
        tv = time.time()
        rec.update(validate(model, vset, device))
        rec["val_time_s"] = time.time() - tv
        history.append(rec)
        elapsed = elapsed0 + (time.time() - t_start)
        _atomic_torch_save({"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch,
                            "history": history, "config": asdict(cfg), "elapsed": elapsed},
                           out_dir / "checkpoint.pt")
        with open(out_dir / "history.json", "w") as f:
            json.dump(history, f, indent=1)
        plot_history(history, out_dir / "training.png")
        log(json.dumps({k: (round(v, 5) if isinstance(v, float) else v) for k, v in rec.items()}))
    elapsed = elapsed0 + (time.time() - t_start)
    prov = {
        "trained_on": {k: int(v) for k, v in sampler.counts().items()},
        "held_out": vset.keys,
        "epochs": cfg.epochs,
        "epochs_done": len(history),
        "examples": int(sum(h["examples"] for h in history)),
        "iterations": total_iters,
        "wall_time_s": round(elapsed, 1),
        "machine": _machine(device),
        "torch": torch.__version__,
        "config": {k: v for k, v in asdict(cfg).items() if k != "progress"},
        "final_validation": {k: v for k, v in (history[-1] if history else {}).items()
                             if k.startswith("val_")},
    }
    return {"model": model, "history": history, "provenance": prov}


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
    g.add_argument("--dataset", choices=["kitti2012", "kitti2015", "middlebury"], default=None,
                   help="keep only pairs of this kind")
    g.add_argument("--include", nargs="+", default=["*"], help="pairs to train on (keys kind/name or patterns)")
    g.add_argument("--holdout", nargs="*", default=[],
                   help="pairs never trained on, used for validation (e.g. kitti2015/000000 middlebury/Cones)")
    g.add_argument("--gt", choices=["all", "noc"], default=d.gt, help="GT pixels that make examples")
    g.add_argument("--max-per-pair", type=int, default=None,
                   help="cap on the locations one pair contributes per epoch (keeps one big image from "
                        "drowning the rest)")
    g = p.add_argument_group("recipe")
    g.add_argument("--epochs", type=int, default=d.epochs)
    g.add_argument("--examples-per-epoch", type=int, default=None,
                   help="patch pairs per epoch (positives + negatives); default: two per usable GT pixel")
    g.add_argument("--batch-size", type=int, default=d.batch_size, help="half positive, half negative")
    g.add_argument("--lr", type=float, default=d.lr)
    g.add_argument("--lr-steps", type=float, nargs="*", default=list(d.lr_steps),
                   help="fractions of the run where the learning rate is multiplied by --lr-factor")
    g.add_argument("--lr-factor", type=float, default=d.lr_factor)
    g.add_argument("--momentum", type=float, default=d.momentum, help="0.9 as in the released code; 0 = plain SGD")
    g.add_argument("--weight-decay", type=float, default=d.weight_decay)
    g.add_argument("--n-lo", type=int, default=d.n_lo)
    g.add_argument("--n-hi", type=int, default=d.n_hi)
    g.add_argument("--p-hi", type=int, default=d.p_hi)
    g.add_argument("--augment", action=argparse.BooleanOptionalAction, default=d.augment,
                   help="geometric/photometric jitter of the released code (not in the paper)")
    g.add_argument("--conv", type=_parse_layers, default=d.conv_layers, help="JSON [[maps, kernel], ...]")
    g.add_argument("--fc", type=_parse_layers, default=d.fc_layers, help="JSON [units, ..., 2]")
    g = p.add_argument_group("run")
    g.add_argument("--out", required=True, help="run folder (checkpoint, history, plot)")
    g.add_argument("--export", default=None, help="weights .npz to write at the end (default OUT/weights.npz)")
    g.add_argument("--resume", default=None, help="checkpoint.pt to continue from")
    g.add_argument("--stop-after", type=int, default=None,
                   help="run at most this many epochs now (continue later with --resume)")
    g.add_argument("--seed", type=int, default=d.seed)
    g.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    g.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
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
    args = build_parser().parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
        try:
            torch.set_num_interop_threads(1)
        except RuntimeError:
            pass
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    commit = _git_commit()  # the code that trains, not whatever HEAD is when it ends
    cfg = TrainConfig(epochs=args.epochs, examples_per_epoch=args.examples_per_epoch,
                      batch_size=args.batch_size, lr=args.lr, lr_steps=tuple(args.lr_steps),
                      lr_factor=args.lr_factor, momentum=args.momentum, weight_decay=args.weight_decay,
                      n_lo=args.n_lo, n_hi=args.n_hi, p_hi=args.p_hi, gt=args.gt,
                      max_per_pair=args.max_per_pair, augment=args.augment, conv_layers=args.conv,
                      fc_layers=args.fc, seed=args.seed, val_examples=args.val_examples,
                      val_pixels=args.val_pixels, val_ndisp=args.val_ndisp, progress=not args.no_progress)
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
        result = train(cfg, train_pairs, val_pairs, device, args.out, resume=args.resume,
                       stop_after=args.stop_after)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    prov = result["provenance"]
    prov["command"] = "python -m mccnn_cl.train.train " + " ".join(shlex.quote(a) for a in
                                                                   (argv if argv is not None else sys.argv[1:]))
    prov["git_commit"] = commit
    prov["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    export = args.export or str(Path(args.out) / "weights.npz")
    result["model"].cpu().to_weights({"training": prov}).save(export)
    print(f"exported {export}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
