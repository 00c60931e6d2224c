"""Self-training on pairs without ground truth (issue 15, item 3).

Pseudo-labels of a pair: run the whole stereo method (:class:`~mccnn_cl.pipeline.StereoMatcher`,
the network's own stereo settings) with ``confidence=True`` and keep the
final disparity D_BF at the pixels that

* the left-right check labels *correct* (``StereoResult.labels == 0``), and
* whose confidence passes ``min_confidence`` (``StereoResult.confidence``:
  the peak-ratio measure of :mod:`mccnn_cl.stages.confidence`,
  (1 - r) / (1 + r) with r = c1' / c2' the ratio of the two lowest local
  minima of the final cost curve measured from the cost's floor), and
* lie inside the cropped domain (not in the ``margin`` border, where the
  pipeline copies the edge outwards), with a finite disparity;

every other pixel is unlabeled (NaN disparity, False mask: what the crop
sampler reads as "no ground truth").  :func:`choose_threshold` picks
``min_confidence`` on *labeled training* pairs from the error of the kept
pixels; the value shipped as :data:`DEFAULT_MIN_CONFIDENCE` and how it was
chosen are in docs/training.md, "Self-training and adapt".

The loop (:func:`self_train`): label every unlabeled pair with the current
network -> fine-tune ``steps`` crop-sampler steps (:func:`mccnn_cl.train.train.train`,
started from the current weights, constant learning rate) on the
pseudo-labeled pairs, optionally mixed with labeled pairs -> relabel ->
... for ``rounds`` rounds.  Each round is one ``train()`` call (momentum
restarts each round, seed ``cfg.seed + round``), so a control run with no
unlabeled pairs goes through exactly the same schedule.  ``share``: the
fraction of the training pixels that come from pseudo-labels when labeled
pairs are mixed in (pseudo-labels are thinned at random to it; crops are
drawn in proportion to labeled pixels).

``python -m mccnn_cl.train.selftrain threshold ...`` prints the kept
fraction / kept error table on labeled pairs and the chosen threshold;
``python -m mccnn_cl.train.selftrain run ...`` runs the loop (the A/B of
docs/training.md).  Users call it through ``mccnn-cl adapt``
(:mod:`mccnn_cl.cli.adapt`).
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from mccnn_cl.evaluation.datasets import StereoPair, discover, to_gray_u8
from mccnn_cl.errors import InputError
from mccnn_cl.models import resolve
from mccnn_cl.weights import ARCHITECTURES, Weights

__all__ = ["DEFAULT_MIN_CONFIDENCE", "UnlabeledPair", "pseudo_labels", "pseudo_pair", "label_pairs",
           "thin", "default_config", "self_train", "provenance", "round_config", "json_safe", "load_unlabeled",
           "threshold_table", "choose_threshold", "main"]

#: The confidence threshold chosen on labeled training pairs with kitti-fst
#: (``threshold`` sub-command; docs/training.md, "Self-training and adapt").
DEFAULT_MIN_CONFIDENCE = 0.6

PSEUDO_KIND = "pseudo"


@dataclass
class UnlabeledPair:
    """Images of a pair to pseudo-label: ``left``/``right`` uint8 (gray or BGR), ``ndisp``: D for it."""

    name: str
    left: np.ndarray
    right: np.ndarray
    ndisp: int


def pseudo_labels(result, min_confidence: float, margin: int | None = None):
    """``(disp, mask)`` from a :class:`~mccnn_cl.pipeline.StereoResult` computed with ``confidence=True``.

    ``mask`` = labels == 0 (left-right correct) & confidence >= ``min_confidence``
    & finite disparity & outside the ``margin``-pixel border (default
    ``result.margin``); ``disp`` = the disparity there, NaN elsewhere.
    """
    if result.confidence is None or result.labels is None:
        raise InputError("pseudo-labels need a StereoResult computed with confidence=True")
    m = result.margin if margin is None else int(margin)
    disp = np.asarray(result.disparity, np.float32)
    mask = (result.labels == 0) & (result.confidence >= np.float32(min_confidence)) & np.isfinite(disp)
    if m > 0:
        mask[:m], mask[-m:], mask[:, :m], mask[:, -m:] = False, False, False, False
    return np.where(mask, disp, np.float32(np.nan)).astype(np.float32), mask


def pseudo_pair(name: str, left, right, disp, mask) -> StereoPair:
    """A StereoPair of kind ``pseudo`` whose "ground truth" is the pseudo-labels (no occlusion mask)."""
    return StereoPair(name=name, left=left, right=right, disp=disp, valid_noc=None, valid_all=mask.copy(),
                      ndisp=None, calib=None, kind=PSEUDO_KIND)


def _matcher(weights, ndisp, ctx, labeler):
    from mccnn_cl.pipeline import StereoMatcher
    if labeler == "census":
        return StereoMatcher(cost="census", max_disparity=ndisp, device=ctx)
    return StereoMatcher(weights=weights, max_disparity=ndisp, device=ctx)


def label_pairs(weights, pairs, min_confidence: float, ctx=None, labeler: str = "network", log=print):
    """Pseudo-label ``pairs`` (UnlabeledPairs) with ``weights`` (or census) through the whole method.

    Returns ``(pseudo StereoPairs, stats)``; ``stats[name]`` = kept fraction
    of the pair's pixels and seconds.  A pair with no kept pixel is skipped
    with a message; when none keeps any pixel it is an InputError (nothing to
    train on), never a silent empty run.
    """
    if labeler not in ("network", "census"):
        raise InputError(f"labeler must be 'network' or 'census', not {labeler!r}")
    from mccnn_cl.opencl.context import ClContext
    ctx = ctx if ctx is not None else ClContext(None)
    matchers, out, stats = {}, [], {}
    for p in pairs:
        if p.ndisp not in matchers:
            matchers[p.ndisp] = _matcher(weights, p.ndisp, ctx, labeler)
        t0 = time.time()
        lg, rg = to_gray_u8(p.left), to_gray_u8(p.right)
        res = matchers[p.ndisp].compute(lg, rg, confidence=True)
        disp, mask = pseudo_labels(res, min_confidence)
        frac = float(mask.mean())
        stats[p.name] = {"kept": round(frac, 4), "lr_correct": round(float((res.labels == 0).mean()), 4),
                         "ndisp": int(p.ndisp), "seconds": round(time.time() - t0, 2)}
        if not mask.any():
            log(f"  {p.name}: no pixel is left-right correct with confidence >= {min_confidence:g}; skipped")
            continue
        log(f"  {p.name}: kept {100 * frac:.1f} % of the pixels (left-right correct "
            f"{100 * stats[p.name]['lr_correct']:.1f} %), {stats[p.name]['seconds']:.1f} s")
        out.append(pseudo_pair(p.name, p.left, p.right, disp, mask))
    for m in matchers.values():
        m.release_buffers()
    if not out:
        raise InputError(f"no pixel of the {len(pairs)} pair(s) passed the left-right check with confidence "
                         f">= {min_confidence:g}: nothing to train on (lower --min-confidence, check --ndisp "
                         "and that the pairs are rectified left/right)")
    return out, stats


def thin(pseudo, target_pixels: int, rng: np.random.Generator):
    """Keep a random ``target_pixels / total`` share of every pair's pseudo-labels (all when fewer)."""
    total = sum(int(p.valid_all.sum()) for p in pseudo)
    if total <= target_pixels:
        return list(pseudo), 1.0
    f = target_pixels / total
    out = []
    for p in pseudo:
        mask = p.valid_all & (rng.random(p.valid_all.shape) < f)
        if mask.any():
            out.append(replace(p, disp=np.where(mask, p.disp, np.float32(np.nan)).astype(np.float32),
                               valid_all=mask))
    return out, f


def _weights_of(model, source: Weights, meta_training: dict) -> Weights:
    """The model's weights with ``source``'s metadata (stereo settings, licence, ...) and new provenance."""
    w = model.cpu().to_weights()
    meta = {k: v for k, v in source.meta.items() if k not in ("training", "name", "description")}
    meta["description"] = (f"{source.meta.get('name') or source.architecture} fine-tuned by self-training "
                           "on pseudo-labels (meta['training'])")
    meta["training"] = meta_training
    return Weights(conv=w.conv, fc=w.fc, meta=meta, architecture=w.architecture).validate()


def _arch_name(w: Weights) -> str:
    return {"mccnn-paper": "paper", "mccnn-fst": "fst", "mccnn-acrt": "acrt"}[w.architecture]


def default_config(source: Weights, **overrides):
    """The crop-sampler recipe of the shipped fst run (docs/training.md), for ``source``'s layers,
    at a constant fine-tuning learning rate (2e-4 unless overridden)."""
    from .train import ARCH_DEFAULTS, TrainConfig
    arch = _arch_name(source)
    ad = ARCH_DEFAULTS[arch]
    kw = dict(arch=arch, sampler="crop", augment=True, subpixel=True, crops_per_step=4, negatives=2,
              lr=2e-4, lr_steps=(), n_lo=ad["n_lo"], n_hi=ad["n_hi"], p_hi=ad["p_hi"],
              conv_layers=source.conv_layers(), fc_layers=source.fc_layers(), progress=False,
              val_examples=0, val_pixels=0, checkpoint_minutes=1e9)
    kw.update(overrides)
    return TrainConfig(**kw)


def self_train(source: Weights, unlabeled, cfg, rounds: int, steps: int, min_confidence: float,
               labeled=(), share: float | None = None, device="cpu", out_dir="runs/selftrain",
               ctx=None, labeler: str = "network", source_name: str | None = None, log=print):
    """The loop of the module docstring; returns ``(Weights, provenance dict)``.

    ``source``: the network to start from (its stereo settings are kept and
    used for labeling).  ``unlabeled``: UnlabeledPairs (may be empty: then
    the loop fine-tunes on ``labeled`` only, the A/B's control).  ``cfg``: a
    TrainConfig (:func:`default_config`); each round runs ``steps`` steps.
    """
    from .train import train
    if source.architecture not in ARCHITECTURES:
        raise InputError(f"cannot self-train a {source.architecture} network")
    if rounds < 1 or steps < 1:
        raise InputError(f"rounds and steps must be >= 1, got {rounds} and {steps}")
    if not 0.0 <= min_confidence <= 1.0:
        raise InputError(f"the confidence threshold must lie in [0, 1], got {min_confidence:g}")
    if share is not None and not 0.0 < share < 1.0:
        raise InputError(f"share must lie in (0, 1), got {share:g}")
    labeled = list(labeled)
    unlabeled = list(unlabeled)
    if not unlabeled and not labeled:
        raise InputError("nothing to train on: no unlabeled and no labeled pairs")
    if ctx is None and (unlabeled or labeler == "census"):
        from mccnn_cl.opencl.context import ClContext
        ctx = ClContext(None)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    labeled_px = sum(int(p.valid_all.sum()) for p in labeled)
    current, rounds_log, t_start = source, [], time.time()
    pseudo_px = {}  # pseudo pair -> pixels it was trained on in the last round that kept any of it
    for r in range(rounds):
        rec = {"round": r + 1}
        train_pairs = list(labeled)
        if unlabeled:
            t0 = time.time()
            log(f"round {r + 1}/{rounds}: labelling {len(unlabeled)} pair(s) "
                f"({'census' if labeler == 'census' else 'current network'}, confidence >= {min_confidence:g})")
            pseudo, stats = label_pairs(current, unlabeled, min_confidence, ctx=ctx, labeler=labeler, log=log)
            rec["label_seconds"] = round(time.time() - t0, 1)
            rec["kept_fraction"] = {k: v["kept"] for k, v in stats.items()}
            rec["skipped"] = [k for k, v in stats.items() if v["kept"] == 0]
            if labeled and share is not None:
                target = int(round(labeled_px * share / (1.0 - share)))
                pseudo, f = thin(pseudo, target, np.random.default_rng([cfg.seed, r, 7]))
                rec["thinned_to"] = round(f, 4)
            rec["pseudo_pixels"] = int(sum(int(p.valid_all.sum()) for p in pseudo))
            pseudo_px.update({p.name: int(p.valid_all.sum()) for p in pseudo})
            train_pairs += pseudo
        rec["labeled_pixels"] = labeled_px
        log(f"round {r + 1}/{rounds}: training {steps} steps on {len(train_pairs)} pair(s)")
        t0 = time.time()
        res = train(round_config(cfg, steps, r), train_pairs, [], device, out_dir / f"round{r + 1}", init=current,
                    log=lambda *_: None)
        h = res["history"][-1]
        rec.update(train_loss=round(h["train_loss"], 5), examples=int(h["examples"]),
                   train_seconds=round(time.time() - t0, 1))
        log(f"round {r + 1}/{rounds}: train loss {h['train_loss']:.4f}, {h['examples']} examples, "
            f"{rec['train_seconds']:.0f} s")
        rounds_log.append(rec)
        current = _weights_of(res["model"], source, {})
    # the training is done: nothing below may lose it
    try:
        prov = provenance(source, source_name, unlabeled, labeled, cfg, rounds, steps, min_confidence, share,
                          labeler, rounds_log, pseudo_px, time.time() - t_start)
    except Exception as exc:  # noqa: BLE001 - a provenance problem must not lose the trained weights
        log(f"warning: the provenance could not be recorded ({type(exc).__name__}: {exc}); "
            "the weights are kept with a short one")
        prov = {"method": "self-training (train/selftrain.py)", "source_weights": source_name,
                "source_training": {"weights": source_name, "licence": source.meta.get("licence")},
                "rounds": int(rounds), "steps_per_round": int(steps),
                "per_round": rounds_log, "provenance_error": f"{type(exc).__name__}: {exc}",
                "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    prov = json_safe(prov)
    return _weights_of(res["model"], source, prov), prov


def round_config(cfg, steps: int, r: int):
    """The TrainConfig that round ``r`` (0-based) runs: one epoch of ``steps`` steps at the constant
    learning rate ``cfg.lr``, seed ``cfg.seed + r``."""
    return replace(cfg, epochs=1, steps_per_epoch=int(steps), lr_steps=(), seed=cfg.seed + r)


def json_safe(obj):
    """``obj`` as JSON holds it (anything else as its text), so that writing the weights never fails on it."""
    return json.loads(json.dumps(obj, default=str))


def provenance(source: Weights, source_name, unlabeled, labeled, cfg, rounds: int, steps: int,
               min_confidence: float, share, labeler: str, rounds_log, pseudo_px: dict, wall_s: float) -> dict:
    """``meta["training"]`` of a self-trained network (:func:`self_train`).

    ``trained_on``: the start's pairs (a dict, or a list of keys as older converted
    files hold), each pseudo-labeled pair with the pixels it was trained on in
    the last round that kept any, each labeled pair with its GT pixels.
    ``config`` is the schedule that ran (:func:`round_config`: every round one
    epoch of ``steps`` steps; ``seeds`` per round); ``source_training`` keeps
    who trained the start on what, its licence and source file."""
    from .train import pairs_of
    src_training = source.meta.get("training") if isinstance(source.meta.get("training"), dict) else {}
    trained_on = pairs_of(src_training.get("trained_on"))
    trained_on.update({f"{PSEUDO_KIND}/{name}": n for name, n in pseudo_px.items()})
    trained_on.update({p.key: int(p.valid_all.sum()) for p in labeled})
    ran = round_config(cfg, steps, 0)
    start = {k: v for k, v in src_training.items() if k in
             ("command", "by", "data", "trained_on", "held_out", "examples", "wall_time_s", "git_commit", "init",
              "source_training")}
    start.update({k: source.meta[k] for k in ("licence", "source") if source.meta.get(k) is not None})
    return {
        "method": "self-training (train/selftrain.py)",
        "source_weights": source_name,
        "source_training": dict(start, weights=source_name, name=source.meta.get("name")),
        "trained_on": trained_on,
        "held_out": list(src_training.get("held_out") or []),
        "unlabeled_pairs": [p.name for p in unlabeled],
        "labeled_pairs": [p.key for p in labeled],
        "labeler": labeler,
        "min_confidence": float(min_confidence),
        "pseudo_label_rule": "left-right correct & peak-ratio confidence >= min_confidence & inside the margin",
        "rounds": int(rounds),
        "steps_per_round": int(steps),
        "total_steps": int(rounds) * int(steps),
        "share": share,
        "per_round": rounds_log,
        "wall_time_s": round(float(wall_s), 1),
        "schedule": (f"{int(rounds)} round(s), each one train() call of 1 epoch x {int(steps)} steps at the constant "
                     f"learning rate {cfg.lr:g}, seed {cfg.seed} + round"),
        "config": dict({k: v for k, v in asdict(ran).items() if k not in ("progress",)},
                       seeds=[cfg.seed + r for r in range(int(rounds))]),
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


# -- choosing the threshold on labeled training pairs -------------------------

def threshold_table(weights, pairs, thresholds, ctx=None, labeler: str = "network", ndisp=None):
    """Per threshold: kept fraction and the kept pixels' error, pooled per kind over labeled ``pairs``.

    Error of a kept pixel: |D_BF - GT| > 3 px (KITTI) or > 2 px (Middlebury), on
    the kept pixels with GT.  Returns ``{kind: [(t, kept, error, n_gt), ...]}``.
    """
    from mccnn_cl.opencl.context import ClContext
    from mccnn_cl.evaluation.scoring import default_max_disparity
    ctx = ctx if ctx is not None else ClContext(None)
    acc = {}
    for p in pairs:
        D = int(ndisp or default_max_disparity(p))
        m = _matcher(weights, D, ctx, labeler)
        lg, rg = p.gray()
        res = m.compute(lg, rg, confidence=True)
        m.release_buffers()
        kind = "kitti" if p.kind.startswith("kitti") else p.kind
        tol = 3.0 if kind == "kitti" else 2.0
        gt = p.valid_all & np.isfinite(np.nan_to_num(p.disp, nan=np.inf))
        err = np.abs(res.disparity - np.nan_to_num(p.disp)) > tol
        rows = acc.setdefault(kind, {t: [0, 0, 0, 0] for t in thresholds})
        for t in thresholds:
            _, mask = pseudo_labels(res, t)
            k = mask & gt
            row = rows[t]
            row[0] += int(mask.sum())
            row[1] += mask.size
            row[2] += int((err & k).sum())
            row[3] += int(k.sum())
    return {kind: [(t, r[0] / r[1], r[2] / max(r[3], 1), r[3]) for t, r in rows.items()]
            for kind, rows in acc.items()}


def choose_threshold(table, target: dict) -> float:
    """The smallest threshold at which every kind's kept error is <= ``target[kind]``."""
    ts = sorted({row[0] for rows in table.values() for row in rows})
    for t in ts:
        if all(next(r for r in rows if r[0] == t)[2] <= target.get(kind, target.get("*", 1.0))
               for kind, rows in table.items()):
            return t
    raise InputError(f"no threshold reaches the target error {target}")


# -- CLI -----------------------------------------------------------------------

def _ndisp_for(key: str, rules) -> int | None:
    for pattern, n in rules:
        if fnmatch.fnmatchcase(key, pattern):
            return n
    return None


def _parse_rule(text):
    pattern, sep, n = text.rpartition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected PATTERN=N, got {text!r}")
    return pattern, int(n)


def load_unlabeled(roots, rules, default=None):
    """UnlabeledPairs discovered under ``roots`` (pairs without GT), D per key from ``rules``."""
    out = []
    for root in roots:
        for ref in discover(root, labeled=False):
            n = _ndisp_for(ref.key, rules) or default
            if n is None:
                raise InputError(f"{ref.key}: no --ndisp rule matches it")
            p = ref.load()
            out.append(UnlabeledPair(name=ref.key, left=p.left, right=p.right, ndisp=int(n)))
    if not out:
        raise InputError(f"no unlabeled pairs under {', '.join(map(str, roots))}")
    return out


def build_parser():
    p = argparse.ArgumentParser(prog="python -m mccnn_cl.train.selftrain", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("threshold", help="kept fraction / kept error per confidence threshold on labeled pairs")
    t.add_argument("--weights", default="kitti-fst")
    t.add_argument("--labeler", choices=["network", "census"], default="network")
    t.add_argument("--threads", type=int, default=None)
    t.add_argument("--data", nargs="+", required=True)
    t.add_argument("--include", nargs="+", default=["*"])
    t.add_argument("--holdout", nargs="*", default=[], help="pairs never looked at (the held-out ones)")
    t.add_argument("--thresholds", type=float, nargs="+",
                   default=[0.0, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5])
    t.add_argument("--target", type=float, nargs="+", default=[0.02],
                   help="kept-pixel error to reach: one value for every kind, or KITTI then Middlebury")
    r = sub.add_parser("run", help="self-training rounds (or the control: --unlabeled omitted)")
    r.add_argument("--weights", default="kitti-fst")
    r.add_argument("--labeler", choices=["network", "census"], default="network")
    r.add_argument("--data", nargs="*", default=[], help="labeled data roots mixed in (with --include/--holdout)")
    r.add_argument("--include", nargs="+", default=["*"])
    r.add_argument("--holdout", nargs="*", default=[])
    r.add_argument("--unlabeled", nargs="*", default=[], help="roots of unlabeled pairs")
    r.add_argument("--ndisp", type=_parse_rule, nargs="*", default=[], metavar="PATTERN=N",
                   help="disparity range per unlabeled key pattern, first match wins")
    r.add_argument("--rounds", type=int, default=2)
    r.add_argument("--steps", type=int, default=250, help="steps per round")
    r.add_argument("--min-confidence", type=float, default=DEFAULT_MIN_CONFIDENCE)
    r.add_argument("--share", type=float, default=None, help="pseudo-label share of the training pixels")
    r.add_argument("--lr", type=float, default=2e-4)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--augment-preset", choices=["kitti", "middlebury"], default=None)
    r.add_argument("--threads", type=int, default=None)
    r.add_argument("--out", required=True)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    import torch
    if getattr(args, "threads", None):
        torch.set_num_threads(args.threads)
    try:
        from .train import select_pairs
        w = resolve(args.weights) if args.labeler == "network" or args.cmd == "run" else None
        if args.cmd == "threshold":
            refs, _ = select_pairs(args.data, args.holdout, args.include)
            pairs = [ref.load() for ref in refs]
            print(f"labeled training pairs: {', '.join(p.key for p in pairs)}", flush=True)
            table = threshold_table(w, pairs, args.thresholds, labeler=args.labeler)
            kinds = sorted(table)
            target = ({"*": args.target[0]} if len(args.target) == 1
                      else dict(zip(["kitti", "middlebury"], args.target)))
            print("threshold  " + "  ".join(f"{k}: kept %, kept error %" for k in kinds))
            for i, t in enumerate(args.thresholds):
                print(f"{t:9.3f}  " + "  ".join(f"{100 * table[k][i][1]:6.2f} {100 * table[k][i][2]:6.2f}"
                                                 for k in kinds))
            print(json.dumps({"chosen": choose_threshold(table, target), "target": target}))
            return 0
        labeled = []
        if args.data:
            refs, _ = select_pairs(args.data, args.holdout, args.include)
            labeled = [ref.load() for ref in refs]
        unl = load_unlabeled(args.unlabeled, args.ndisp) if args.unlabeled else []
        cfg = default_config(w, lr=args.lr, seed=args.seed, augment_preset=args.augment_preset)
        device = "cuda" if torch.cuda.is_available() else "cpu"
        out = Path(args.out)
        t0 = time.time()
        w2, prov = self_train(w, unl, cfg, args.rounds, args.steps, args.min_confidence, labeled=labeled,
                              share=args.share, device=device, out_dir=out, labeler=args.labeler,
                              source_name=str(args.weights), log=lambda *a: print(*a, flush=True))
        prov["command"] = "python -m mccnn_cl.train.selftrain " + " ".join(argv if argv is not None
                                                                           else sys.argv[1:])
        w2.meta["training"] = prov
        w2.save(out / "weights.npz")
        print(f"exported {out / 'weights.npz'} ({time.time() - t0:.0f} s)", flush=True)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    from ..cli import run_entry_point  # a reader of stdout gone: exit 141, quietly

    raise SystemExit(run_entry_point(main))
