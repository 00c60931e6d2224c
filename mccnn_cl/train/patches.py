"""On-the-fly sampler of training patch pairs, as in the paper's "Creating the dataset".

For every left pixel p = (x, y) with known disparity d we make one positive
pair <P_L(p), P_R(x - d + o_pos, y)>, o_pos drawn uniformly from
{-P_hi, ..., P_hi}, and one negative pair <P_L(p), P_R(x - d + o_neg, y)>,
o_neg drawn uniformly from {-N_hi, ..., -N_lo, N_lo, ..., N_hi}
(paper: N_lo = 4, N_hi = 8, P_hi = 1, 9x9 patches).

Choices the paper leaves open (documented in docs/training.md):

* the right patch centre is ``floor(x - d + 0.5) + o``: the GT disparity is
  rounded to the nearest integer (the released code warps sub-pixel instead);
* a location is *skipped* for the epoch when its left patch, its positive or
  its negative right patch would leave the image (offsets are redrawn every
  epoch, so a location near the border is skipped only in some epochs);
* a batch of ``B`` locations gives ``B`` positive and ``B`` negative pairs
  (the paper's batch of 128 = 64 + 64, as in the released code);
* images are gray (colour → luminance, cv2 BGR2GRAY), each normalised by its
  own mean and standard deviation.

Nothing is materialised: the sampler keeps one flat float32 buffer of all
normalised images plus per-location index arrays, and cuts patches out with
one fancy-indexing gather per batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mccnn_cl.evaluation.datasets import StereoPair
from mccnn_cl.errors import InputError
from mccnn_cl.imageops import standardise as normalise  # the network's, bit for bit (inference's too)


def training_view(p: StereoPair, use: str, patch_size: int):
    """(left gray, right gray, valid GT mask) of a pair that examples are drawn
    from: ``use`` "noc" takes the non-occluded mask where the pair has one, else
    all GT; a pair without GT or smaller than one patch is an InputError.
    Shared by the patch and crop samplers."""
    if p.disp is None:
        raise InputError(f"{p.key}: no ground truth, cannot make training examples")
    valid = p.valid_noc if (use == "noc" and p.valid_noc is not None) else p.valid_all
    left, right = p.gray()
    h, w = left.shape
    if h < patch_size or w < patch_size:
        raise InputError(f"{p.key}: image {w}x{h} smaller than a {patch_size}x{patch_size} patch")
    return left, right, valid

__all__ = ["PatchSampler", "Batch", "normalise"]


@dataclass
class Batch:
    """Patch pairs: ``left``/``right`` float32 (N, 1, P, P), ``labels`` int64 (N,) with 1 = good match."""

    left: np.ndarray
    right: np.ndarray
    labels: np.ndarray


class PatchSampler:
    """Positive/negative patch pairs from a list of :class:`StereoPair` with ground truth.

    ``patch_size``: P (odd).  ``use``: which GT pixels make examples, ``"all"``
    (``valid_all``: the paper trains on every pixel with known disparity) or
    ``"noc"`` (``valid_noc`` where available).  ``max_per_pair``: an epoch
    draws from each pair at most this many locations (``None``: no cap), so
    one big image (Aloe: 1.4 M GT pixels) does not drown the others.
    """

    def __init__(self, pairs, patch_size: int = 9, n_lo: int = 4, n_hi: int = 8, p_hi: int = 1,
                 use: str = "all", max_per_pair: int | None = None):
        if patch_size < 1 or patch_size % 2 == 0:
            raise InputError(f"patch_size must be odd and positive, got {patch_size}")
        if not (0 <= p_hi < n_lo <= n_hi):
            raise InputError(f"need 0 <= P_hi < N_lo <= N_hi, got P_hi={p_hi}, N_lo={n_lo}, N_hi={n_hi}")
        if use not in ("all", "noc"):
            raise InputError(f"use must be 'all' or 'noc', got {use!r}")
        self.patch_size, self.r = patch_size, patch_size // 2
        self.n_lo, self.n_hi, self.p_hi = n_lo, n_hi, p_hi
        self.max_per_pair = max_per_pair
        self.keys, self.widths, self.heights, self.bases = [], [], [], []
        chunks, self.loc = [], []  # per pair: (x, y, xr0) int32 arrays; xr0 = rounded x - d
        base = 0
        r = self.r
        for p in pairs:
            left, right, valid = training_view(p, use, patch_size)
            h, w = left.shape
            chunks += [normalise(left).ravel(), normalise(right).ravel()]
            ys, xs = np.nonzero(valid)
            d = p.disp[ys, xs]
            xr0 = np.floor(xs - d + 0.5).astype(np.int64)
            # Left patch inside the image; right centre of the exact match inside too.
            keep = (xs >= r) & (xs < w - r) & (ys >= r) & (ys < h - r) & (xr0 >= r) & (xr0 < w - r)
            self.loc.append((xs[keep].astype(np.int32), ys[keep].astype(np.int32), xr0[keep].astype(np.int32)))
            self.keys.append(p.key)
            self.widths.append(w)
            self.heights.append(h)
            self.bases.append(base)
            base += 2 * h * w
        if not self.keys:
            raise InputError("no training pairs given")
        self.flat = np.concatenate(chunks)
        self.widths = np.array(self.widths, np.int64)
        self.bases = np.array(self.bases, np.int64)  # left image at base, right at base + h*w
        self.heights = np.array(self.heights, np.int64)
        dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
        self._dy, self._dx = dy.ravel(), dx.ravel()

    # -- bookkeeping ----------------------------------------------------
    def counts(self) -> dict:
        """Usable GT locations per pair key."""
        return {k: int(len(l[0])) for k, l in zip(self.keys, self.loc)}

    def locations_per_epoch(self) -> dict:
        """Locations an epoch draws from each pair when it takes everything (after the cap)."""
        cap = self.max_per_pair
        return {k: (n if cap is None else min(n, cap)) for k, n in self.counts().items()}

    # -- epoch plan -----------------------------------------------------
    def epoch(self, rng: np.random.Generator, n_locations: int | None = None):
        """Plan one epoch: returns (pair index, x, y, x_pos, x_neg) int arrays, shuffled.

        ``n_locations``: how many locations to draw (``None``: all after the
        per-pair cap), split between pairs in proportion to their capped
        counts, each pair's share drawn without replacement (with replacement
        only if the share exceeds the pair).  Locations whose positive or
        negative right patch leaves the image are dropped, so slightly fewer
        than ``n_locations`` come back.
        """
        per = self.locations_per_epoch()
        sizes = np.array([per[k] for k in self.keys], np.float64)
        total = sizes.sum()
        if total == 0:
            raise InputError("the training pairs have no usable ground-truth pixels")
        want = int(total) if n_locations is None else int(n_locations)
        shares = np.floor(sizes / total * want).astype(np.int64)
        # Hand the rounding remainder to the largest fractional parts (deterministic).
        rem = want - shares.sum()
        if rem > 0:
            frac = sizes / total * want - shares
            shares[np.argsort(-frac, kind="stable")[:rem]] += 1
        out = []
        for i, (xs, ys, xr0) in enumerate(self.loc):
            k = int(shares[i])
            n = len(xs)
            if k == 0 or n == 0:
                continue
            idx = rng.choice(n, size=k, replace=k > n)
            x, y, c = xs[idx], ys[idx], xr0[idx]
            o_pos = rng.integers(-self.p_hi, self.p_hi + 1, size=k)
            mag = rng.integers(self.n_lo, self.n_hi + 1, size=k)
            o_neg = np.where(rng.random(k) < 0.5, -mag, mag)
            xp, xn = c + o_pos, c + o_neg
            w = int(self.widths[i])
            ok = (xp >= self.r) & (xp < w - self.r) & (xn >= self.r) & (xn < w - self.r)
            out.append((np.full(int(ok.sum()), i, np.int32), x[ok], y[ok], xp[ok].astype(np.int32),
                        xn[ok].astype(np.int32)))
        plan = [np.concatenate(a) for a in zip(*out)]
        perm = rng.permutation(len(plan[0]))
        return tuple(a[perm] for a in plan)

    # -- patches --------------------------------------------------------
    def patches(self, img: np.ndarray, x: np.ndarray, y: np.ndarray, right: bool) -> np.ndarray:
        """Gather (N, 1, P, P) float32 patches centred at (x, y) of pair ``img``'s left or right image."""
        w = self.widths[img]
        base = self.bases[img] + (self.heights[img] * w if right else 0)
        idx = (base + y.astype(np.int64) * w + x)[:, None] + self._dy[None, :] * w[:, None] + self._dx[None, :]
        p = self.patch_size
        return self.flat[idx].reshape(-1, 1, p, p)

    def batch(self, plan, start: int, stop: int) -> Batch:
        """Patch pairs for locations ``plan[..][start:stop]``: positives first, then negatives."""
        img, x, y, xp, xn = (a[start:stop] for a in plan)
        lp = self.patches(img, x, y, right=False)
        left = np.concatenate([lp, lp])
        right = np.concatenate([self.patches(img, xp, y, right=True), self.patches(img, xn, y, right=True)])
        n = len(img)
        labels = np.concatenate([np.ones(n, np.int64), np.zeros(n, np.int64)])
        return Batch(left=left, right=right, labels=labels)
