"""Evaluation of a torch MC-CNN during and after training (``@torch.no_grad()``, dicts out).

Two measures, both on pairs held out of training:

* :func:`patch_metrics`: cross-entropy and accuracy on a fixed set of
  positive/negative patch pairs drawn like the training examples;
* :func:`wta_error`: the 3-px error of winner-take-all on the raw CNN cost
  ``C_CNN(p, d) = softmax(net(P_L(p), P_R(p - d)))[bad match]`` at sampled
  ground-truth pixels, every disparity ``0 <= d < D`` with ``x - d`` inside
  the cropped domain (the project's validity rule ``d <= x``, in volume
  coordinates).  Features are computed only on the rows that hold the sampled
  pixels, so it stays cheap on a CPU.

:func:`make_validation` draws both samples once (seeded) so every epoch is
measured on the same pixels and patches.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from mccnn_cl.errors import InputError

from .patches import Batch, PatchSampler, normalise

__all__ = ["ValidationSet", "make_validation", "patch_metrics", "wta_error", "validate", "census_wta_error",
           "KITTI_NDISP"]

KITTI_NDISP = 228  # the paper's KITTI disparity range


@dataclass
class _PixelSample:
    key: str
    left: np.ndarray   # (H, W) normalised float32
    right: np.ndarray
    xs: np.ndarray     # image coordinates of the sampled pixels
    ys: np.ndarray
    gt: np.ndarray     # float32 GT disparities there
    ndisp: int
    gt_mask: str       # "noc" or "all"


@dataclass
class ValidationSet:
    """Fixed held-out samples: one :class:`Batch` of patch pairs and per-pair pixel samples."""

    patches: Batch | None
    pixels: list = field(default_factory=list)

    @property
    def keys(self) -> list:
        return [p.key for p in self.pixels]


def make_validation(pairs, patch_size: int, n_examples: int = 4000, n_pixels: int = 3000,
                    rows_per_pair: int = 48, seed: int = 1234, n_lo: int = 4, n_hi: int = 8,
                    p_hi: int = 1, ndisp: int | None = None) -> ValidationSet:
    """Draw the validation samples from held-out ``pairs`` (StereoPairs with GT).

    ``n_examples`` patch pairs (half positive) drawn like training examples
    from all GT pixels; ``n_pixels`` WTA pixels split evenly between the pairs,
    taken from ``rows_per_pair`` random rows of each, among the *non-occluded*
    GT pixels where the pair has a non-occlusion mask (all GT otherwise), with
    ``gt < D``.  ``D`` = ``ndisp`` if given, else the pair's own ``ndisp``
    (Middlebury calib.txt), else 228 (KITTI).
    """
    pairs = list(pairs)
    if not pairs:
        return ValidationSet(patches=None, pixels=[])
    rng = np.random.default_rng(seed)
    r = patch_size // 2
    patches = None
    if n_examples > 0:
        sampler = PatchSampler(pairs, patch_size=patch_size, n_lo=n_lo, n_hi=n_hi, p_hi=p_hi)
        plan = sampler.epoch(rng, n_locations=max(1, n_examples // 2))
        patches = sampler.batch(plan, 0, len(plan[0]))
    pixels = []
    per_pair = max(1, n_pixels // len(pairs))
    for p in pairs:
        if p.disp is None:
            raise InputError(f"{p.key}: no ground truth, cannot validate on it")
        D = int(ndisp or p.ndisp or KITTI_NDISP)
        use_noc = p.valid_noc is not None
        mask = (p.valid_noc if use_noc else p.valid_all).copy()
        h, w = mask.shape
        mask[:r], mask[h - r:], mask[:, :r], mask[:, w - r:] = False, False, False, False
        mask &= np.nan_to_num(p.disp, nan=np.inf) < D
        rows = np.flatnonzero(mask.any(axis=1))
        if len(rows) == 0:
            raise InputError(f"{p.key}: no usable ground-truth pixels for validation")
        rows = np.sort(rng.choice(rows, size=min(rows_per_pair, len(rows)), replace=False))
        sub = np.zeros_like(mask)
        sub[rows] = mask[rows]
        ys, xs = np.nonzero(sub)
        pick = rng.choice(len(ys), size=min(per_pair, len(ys)), replace=False)
        ys, xs = ys[pick], xs[pick]
        lg, rg = p.gray()
        pixels.append(_PixelSample(key=p.key, left=normalise(lg), right=normalise(rg), xs=xs, ys=ys,
                                   gt=p.disp[ys, xs].astype(np.float32), ndisp=D,
                                   gt_mask="noc" if use_noc else "all"))
    return ValidationSet(patches=patches, pixels=pixels)


@torch.no_grad()
def patch_metrics(model, batch: Batch, device, chunk: int = 4096) -> dict:
    """Mean training loss and accuracy of ``model`` on the patch pairs of ``batch``.

    ``batch`` holds n positives then n negatives, paired by position.  The
    loss is the architecture's (:meth:`MCCNN.loss`: per example for paper
    and acrt, per pair for fst).  Accuracy: paper, the argmax class; acrt,
    the sigmoid on the right side of 0.5; fst (a score, no threshold), the
    fraction of pairs where the positive scores above the negative.
    """
    model.eval()
    outs = []
    n = len(batch.labels)
    for s in range(0, n, chunk):
        left = torch.from_numpy(batch.left[s:s + chunk]).to(device)
        right = torch.from_numpy(batch.right[s:s + chunk]).to(device)
        outs.append(model(left, right))
    out = torch.cat(outs)
    lab = torch.from_numpy(batch.labels).to(device)
    half = n // 2
    if not (bool((lab[:half] == 1).all()) and bool((lab[half:] == 0).all())):
        raise InputError("patch batch must hold positives first, then as many negatives")
    arch = getattr(model, "architecture", "mccnn-paper")
    if arch == "mccnn-fst":
        loss = float(model.loss(out[:half], out[half:], reduction="sum")) / half
        correct, total = int((out[:half] > out[half:]).sum()), half
    else:
        loss = float(model.loss(out[:half], out[half:], reduction="sum")) / n
        good = out.argmax(1) == 1 if out.dim() == 2 else out < 0
        correct, total = int((good == (lab == 1)).sum()), n
    return {"loss": loss, "accuracy": correct / total, "n": n}


@torch.no_grad()
def row_features(model, img: np.ndarray, rows: np.ndarray, device) -> torch.Tensor:
    """L1..L3 features of image rows ``rows`` (image coordinates): (len(rows), maps, W - P + 1).

    Row y's features come from the band of rows y - r .. y + r, the same
    numbers the fully convolutional pass over the whole image gives there.
    """
    r = model.patch_size // 2
    bands = np.stack([img[y - r:y + r + 1] for y in rows])[:, None]  # (R, 1, P, W)
    f = model.features(torch.from_numpy(np.ascontiguousarray(bands)).to(device))
    return f[:, :, 0, :]


@torch.no_grad()
def wta_costs(model, left_feat: torch.Tensor, right_feat: torch.Tensor, xv: torch.Tensor,
              ndisp: int, chunk: int = 64) -> torch.Tensor:
    """C_CNN for pixels at cropped-domain columns ``xv`` and disparities 0..ndisp-1.

    ``left_feat``/``right_feat``: (N, maps, Wc) features of each pixel's row.
    Returns (N, ndisp) costs (:meth:`MCCNN.cost`: paper softmax[bad], fst -f_L.f_R, acrt sigmoid),
    +inf where ``d > xv`` (right pixel outside the cropped domain).
    """
    n, maps, wc = left_feat.shape
    d = torch.arange(ndisp, device=left_feat.device)
    out = torch.empty(n, ndisp, device=left_feat.device)
    for s in range(0, n, chunk):
        lf = left_feat[s:s + chunk]
        rf = right_feat[s:s + chunk]
        x = xv[s:s + chunk]
        m = len(x)
        fl = lf[torch.arange(m), :, x]                       # (m, maps)
        xr = (x[:, None] - d[None, :])                       # (m, D)
        valid = xr >= 0
        fr = rf[torch.arange(m)[:, None], :, xr.clamp(min=0)]  # (m, D, maps)
        cost = model.cost(model.head(fl[:, None, :].expand(-1, ndisp, -1), fr))
        out[s:s + chunk] = torch.where(valid, cost, torch.full_like(cost, float("inf")))
    return out


@torch.no_grad()
def wta_error(model, vset: ValidationSet, device, threshold: float = 3.0) -> dict:
    """Winner-take-all error on the raw CNN cost at the validation pixels.

    Returns ``{"err3": fraction with |d_WTA - gt| > threshold over all pairs,
    "per_pair": {key: fraction}, "n": pixels, "mean_abs": mean |d - gt|}``.
    """
    model.eval()
    r = model.patch_size // 2
    bad, total, abs_sum, per_pair = 0, 0, 0.0, {}
    for px in vset.pixels:
        rows, inv = np.unique(px.ys, return_inverse=True)
        lf = row_features(model, px.left, rows, device)
        rf = row_features(model, px.right, rows, device)
        idx = torch.from_numpy(inv).to(device)
        xv = torch.from_numpy((px.xs - r).astype(np.int64)).to(device)
        costs = wta_costs(model, lf[idx], rf[idx], xv, px.ndisp)
        d = costs.argmin(dim=1).cpu().numpy().astype(np.float32)
        err = np.abs(d - px.gt)
        nb = int((err > threshold).sum())
        per_pair[px.key] = nb / len(err)
        bad += nb
        total += len(err)
        abs_sum += float(err.sum())
    if total == 0:
        return {"err3": float("nan"), "per_pair": {}, "n": 0, "mean_abs": float("nan")}
    return {"err3": bad / total, "per_pair": per_pair, "n": total, "mean_abs": abs_sum / total}


def census_wta_error(vset: ValidationSet, window: int = 9, threshold: float = 3.0) -> dict:
    """Baseline for context: WTA on a ``window``² census cost (Hamming distance) at the same pixels.

    Same pixels, disparity range and validity rule as :func:`wta_error`
    (the census window equals the 9x9 patch, so the same cropped domain);
    ties go to the smallest disparity.  Works on the normalised images (the
    census only compares intensities, so normalisation does not change it).
    """
    r = window // 2
    bad, total, per_pair = 0, 0, {}
    for px in vset.pixels:
        h, w = px.left.shape
        offs = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if (dy, dx) != (0, 0)]

        def codes(img, y):  # (W - 2r, bits) census of row y, columns r .. W-r-1
            c = img[y, r:w - r]
            return np.stack([img[y + dy, r + dx:w - r + dx] < c for dy, dx in offs], axis=1)
        errs = []
        rows = {y: (codes(px.left, y), codes(px.right, y)) for y in np.unique(px.ys)}
        for x, y, g in zip(px.xs, px.ys, px.gt):
            cl, cr = rows[y]
            xv = x - r
            nd = min(px.ndisp, xv + 1)
            cost = (cr[xv - np.arange(nd)] != cl[xv]).sum(axis=1)
            errs.append(abs(int(np.argmin(cost)) - g))
        errs = np.array(errs)
        per_pair[px.key] = float((errs > threshold).mean())
        bad += int((errs > threshold).sum())
        total += len(errs)
    return {"err3": bad / max(total, 1), "per_pair": per_pair, "n": total}


@torch.no_grad()
def validate(model, vset: ValidationSet, device) -> dict:
    """Both measures: ``{"val_loss", "val_accuracy", "val_err3", "val_err3_per_pair", ...}``."""
    out = {}
    if vset.patches is not None:
        pm = patch_metrics(model, vset.patches, device)
        out.update(val_loss=pm["loss"], val_accuracy=pm["accuracy"], val_examples=pm["n"])
    if vset.pixels:
        we = wta_error(model, vset, device)
        out.update(val_err3=we["err3"], val_err3_per_pair=we["per_pair"], val_pixels=we["n"],
                   val_mean_abs=we["mean_abs"])
    return out


# -- CLI: evaluate exported weights on held-out pairs ----------------------------------

def main(argv=None) -> int:
    """``python -m mccnn_cl.train.validation --weights W.npz --data DIR --pairs KEY ...``: JSON to stdout."""
    import argparse
    import fnmatch
    import json
    import sys

    from mccnn_cl.evaluation.datasets import discover
    from mccnn_cl.weights import Weights

    from .model import MCCNN

    ap = argparse.ArgumentParser(prog="python -m mccnn_cl.train.validation",
                                 description="Patch loss and WTA 3-px error of a weights file on pairs with GT.")
    ap.add_argument("--weights", default=None, help="weights .npz (default: the shipped model)")
    ap.add_argument("--data", nargs="+", required=True, help="dataset folders (any supported layout)")
    ap.add_argument("--pairs", nargs="+", default=["*"], help="pair keys or patterns (kind/name)")
    ap.add_argument("--examples", type=int, default=4000, help="held-out patch pairs for the loss")
    ap.add_argument("--pixels", type=int, default=3000, help="WTA pixels, split between the pairs")
    ap.add_argument("--rows", type=int, default=48, help="random rows per pair the pixels come from")
    ap.add_argument("--ndisp", type=int, default=None, help="WTA disparity range (default: pair's, 228 KITTI)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--baseline", action="store_true",
                    help="also report a 9x9 census WTA error at the same pixels, for context")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        model = MCCNN.from_weights(Weights.load(args.weights)).eval()
        refs = [r for root in args.data for r in discover(root, labeled=True)
                if any(fnmatch.fnmatchcase(r.key, p) or r.key.split("/", 1)[-1] == p for p in args.pairs)]
        if not refs:
            raise InputError("no pair matches --pairs")
        pairs = [r.load() for r in refs]
        vset = make_validation(pairs, model.patch_size, n_examples=args.examples, n_pixels=args.pixels,
                               rows_per_pair=args.rows, seed=args.seed, ndisp=args.ndisp)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    res = validate(model, vset, "cpu")
    res["pairs"] = [r.key for r in refs]
    if args.baseline:
        b = census_wta_error(vset)
        res.update(census_err3=b["err3"], census_err3_per_pair=b["per_pair"])
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    from ..cli import run_entry_point  # a reader of stdout gone: exit 141, quietly

    raise SystemExit(run_entry_point(main))
