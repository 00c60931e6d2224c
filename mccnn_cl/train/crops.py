"""Fully convolutional crop training: many examples from one feature map per crop.

The networks use valid convolutions and no pooling, so the feature of a P x P
patch centred at pixel q equals the feature map of a larger crop at q (minus
the margin r = P // 2).  A :class:`CropSampler` step therefore cuts (and
optionally warps) a left crop around a random anchor GT pixel and a wider
right crop around its match (the right crop spans ``spread`` extra columns
each side, enough for x - d + o of the crop's other GT pixels), and lists
for the GT pixels p inside it the positions, in the two feature maps, of
P_L(p), the positive P_R(p - d + o_pos) (|o_pos| <= p_hi) and ``negatives``
negatives P_R(p - d + o_neg) (n_lo <= |o_neg| <= n_hi).  Training runs the
conv stack once per crop and gathers features at those positions (:func:`gather`),
then applies the architecture's head and loss.

``subpixel=False`` (integer mode): d rounded to the nearest pixel, integer
offsets, no warp: every position is an integer and the gathered features are
exactly the patch features (tested).  ``subpixel=True``: exact GT d and
continuous offsets as in the released code; positions are fractional and the
raw (pre-normalisation) feature maps are sampled bilinearly.  ``augment``:
one affine warp per crop for both images (rotation, horizontal scale, shear;
the right image may get extra perturbations) and brightness/contrast, the
released code's ranges; GT positions are mapped through the same warp, so
positive and negative positions stay consistent (fractional, hence
bilinear).  Examples whose left or right centre leaves the image (by r) or
the crop's feature map are dropped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from mccnn_cl.evaluation.datasets import dataset_of
from mccnn_cl.errors import InputError

from .patches import normalise, training_view

__all__ = ["Augment", "CropSampler", "CropBatch", "gather", "KITTI_AUGMENT", "MIDDLEBURY_AUGMENT", "BALANCES",
           "pair_weights"]


@dataclass(frozen=True)
class Augment:
    """The released code's augmentation ranges (main.lua); ``d_*`` act on the right image only."""

    rotate: float = 7.0        # degrees
    hscale: float = 0.9        # horizontal scale drawn from [hscale, 1]
    scale: float = 1.0         # both axes, [scale, 1]
    hshear: float = 0.1
    brightness: float = 0.7
    contrast: float = 1.3
    d_vtrans: float = 0.0
    d_rotate: float = 0.0
    d_hscale: float = 1.0
    d_hshear: float = 0.0
    d_brightness: float = 0.3
    d_contrast: float = 1.0


KITTI_AUGMENT = Augment()
MIDDLEBURY_AUGMENT = Augment(rotate=28.0, hscale=0.8, scale=0.8, hshear=0.1, brightness=1.3, contrast=1.1,
                             d_vtrans=1.0, d_rotate=3.0, d_hscale=0.9, d_hshear=0.3, d_brightness=0.7,
                             d_contrast=1.1)

#: How a sampler spreads its crops over the pairs (``CropSampler(balance=)``).
BALANCES = ("pixels", "pair", "dataset")


def pair_weights(counts, datasets, balance: str = "pixels", max_per_pair: int | None = None) -> np.ndarray:
    """Probability of drawing each pair's crops (sums to 1).

    ``pixels``: in proportion to the pair's usable GT pixels (capped at
    ``max_per_pair``); ``pair``: every pair alike; ``dataset``: every dataset
    (``datasets[i]``, e.g. kitti / middlebury / middeval3 / eth3d) an equal
    share, split within it in proportion to the capped GT pixels.
    """
    if balance not in BALANCES:
        raise InputError(f"balance must be one of {', '.join(BALANCES)}, got {balance!r}")
    w = np.array([n if max_per_pair is None else min(n, max_per_pair) for n in counts], np.float64)
    if balance == "pair":
        w = (w > 0).astype(np.float64)
    elif balance == "dataset":
        ds = list(datasets)
        tot = {d: sum(wi for wi, di in zip(w, ds) if di == d) for d in set(ds)}
        live = [d for d, t in tot.items() if t > 0]
        w = np.array([wi / tot[di] / len(live) if tot[di] > 0 else 0.0 for wi, di in zip(w, ds)])
    s = float(w.sum())
    if s == 0:
        raise InputError("the training pairs have no usable ground-truth pixels")
    return w / s


@dataclass
class CropBatch:
    """Crops and example positions (feature-map coordinates, x then y).

    ``left`` (B, 1, Hc, Wc), ``right`` (B, 1, Hc, Wr); ``crop`` (N,) crop index
    of each example; ``ql`` (N, 2) left positions; ``qp`` (N, 2) positive;
    ``qn`` (N, K, 2) negatives; ``exact``: all positions are integers.
    """

    left: torch.Tensor
    right: torch.Tensor
    crop: torch.Tensor
    ql: torch.Tensor
    qp: torch.Tensor
    qn: torch.Tensor
    exact: bool
    src: dict | None = None  # source coordinates per example (pair, x, y, x_pos, x_neg), for tests

    @property
    def n(self) -> int:
        return int(self.crop.shape[0])


def gather(fmap: torch.Tensor, crop: torch.Tensor, q: torch.Tensor, exact: bool) -> torch.Tensor:
    """Features of ``fmap`` (B, C, H, W) at positions ``q`` (..., 2) (x, y) of crops ``crop`` (...) -> (..., C).

    ``exact``: integer positions, plain indexing; else bilinear (grid_sample,
    align_corners=True: integer positions give the map's values exactly).
    """
    if exact:
        qi = q.round().long()
        return fmap[crop, :, qi[..., 1], qi[..., 0]]
    b, c, h, w = fmap.shape
    shape = crop.shape
    crop, q = crop.reshape(-1), q.reshape(-1, 2)
    out = torch.empty(crop.shape[0], c, dtype=fmap.dtype, device=fmap.device)
    scale = torch.tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)], dtype=q.dtype, device=q.device)
    parts = []
    order = torch.argsort(crop, stable=True)
    counts = torch.bincount(crop, minlength=b).tolist()
    s = 0
    for i, k in enumerate(counts):
        if k == 0:
            continue
        idx = order[s:s + k]
        s += k
        g = (q[idx] * scale - 1.0).to(fmap.dtype).view(1, 1, k, 2)
        v = F.grid_sample(fmap[i:i + 1], g, mode="bilinear", padding_mode="border", align_corners=True)
        parts.append((idx, v[0, :, 0, :].t()))
    for idx, v in parts:
        out = out.index_copy(0, idx, v)
    return out.view(*shape, c)


class CropSampler:
    """Crop pairs plus example positions from StereoPairs with GT (see module docstring).

    ``patch_size``: the net's P.  ``crop``: (h, w) of the left feature map
    (odd; the left image crop is h + P - 1 by w + P - 1).  ``spread``: extra
    right feature-map columns each side.  ``per_crop``: at most this many GT
    pixels per crop.  ``negatives``: negatives per GT pixel.  ``max_per_pair``:
    crops are drawn from pairs in proportion to min(GT pixels, cap).
    """

    def __init__(self, pairs, patch_size: int, p_hi: float = 1, n_lo: float = 4, n_hi: float = 10,
                 crop=(47, 47), spread: int = 32, per_crop: int = 1024, negatives: int = 1,
                 subpixel: bool = False, augment=None, use: str = "all",
                 max_per_pair: int | None = None, balance: str = "pixels", offsets: dict | None = None):
        if not (0 <= p_hi < n_lo <= n_hi):
            raise InputError(f"need 0 <= P_hi < N_lo <= N_hi, got P_hi={p_hi}, N_lo={n_lo}, N_hi={n_hi}")
        for ds, (a, b, c) in (offsets or {}).items():
            if not (0 <= a < b <= c):
                raise InputError(f"{ds} offsets: need 0 <= P_hi < N_lo <= N_hi, got {a}, {b}, {c}")
            if not subpixel and any(float(v) != int(v) for v in (a, b, c)):
                raise InputError("integer mode needs integer offsets (use subpixel=True for fractional ones)")
        h, w = crop
        if h < 1 or w < 1 or h % 2 == 0 or w % 2 == 0:
            raise InputError(f"crop sizes must be odd and positive, got {crop}")
        if not subpixel and any(float(v) != int(v) for v in (p_hi, n_lo, n_hi)):
            raise InputError("integer mode needs integer offsets (use subpixel=True for fractional ones)")
        self.r = patch_size // 2
        self.patch_size = patch_size
        self.p_hi, self.n_lo, self.n_hi = p_hi, n_lo, n_hi
        self.h, self.w, self.spread = h, w, int(spread)
        self.wr = w + 2 * self.spread
        self.per_crop, self.negatives = int(per_crop), int(negatives)
        self.subpixel, self.aug = subpixel, augment
        self.keys, self.imgs, self.gt, self.weights = [], [], [], []
        self.pair_aug, self.pair_off, datasets = [], [], []
        for p in pairs:
            ds = dataset_of(p.key)
            datasets.append(ds)
            self.pair_aug.append(augment.get(ds) if isinstance(augment, dict) else augment)
            self.pair_off.append(tuple((offsets or {}).get(ds, (p_hi, n_lo, n_hi))))
            lg, rg, valid = training_view(p, use, patch_size)
            hh, ww = lg.shape
            disp = np.where(valid, np.nan_to_num(p.disp, nan=0.0), 0.0).astype(np.float32)
            ys, xs = np.nonzero(valid)
            self.keys.append(p.key)
            self.imgs.append((torch.from_numpy(normalise(lg))[None, None], torch.from_numpy(normalise(rg))[None, None]))
            self.gt.append((valid.copy(), disp, xs.astype(np.int32), ys.astype(np.int32)))
            n = len(xs)
            self.weights.append(n if max_per_pair is None else min(n, max_per_pair))
        if not self.keys:
            raise InputError("no training pairs given")
        self.datasets = datasets
        self.prob = pair_weights([len(g[2]) for g in self.gt], datasets, balance, max_per_pair)
        self.augmenting = any(a is not None for a in self.pair_aug)

    def counts(self) -> dict:
        return {k: int(len(g[2])) for k, g in zip(self.keys, self.gt)}

    # -- geometry -------------------------------------------------------
    def _draw_warp(self, rng, a):
        """Forward linear maps (source -> crop) for left and right, and photometric (c, b) pairs (``a``: Augment)."""
        if a is None:
            eye = np.eye(2)
            return eye, eye, 0.0, (1.0, 0.0), (1.0, 0.0)
        u = rng.uniform
        s = u(a.scale, 1.0)
        sx, sy = s * u(a.hscale, 1.0), s
        sh = u(-a.hshear, a.hshear)
        phi = u(-a.rotate, a.rotate) * math.pi / 180
        b = u(-a.brightness, a.brightness)
        c = u(1 / a.contrast, a.contrast)
        sx_ = sx * u(a.d_hscale, 1.0)
        sh_ = sh + u(-a.d_hshear, a.d_hshear)
        ty_ = u(-a.d_vtrans, a.d_vtrans)
        phi_ = phi + u(-a.d_rotate, a.d_rotate) * math.pi / 180
        b_ = b + u(-a.d_brightness, a.d_brightness)
        c_ = c * u(1 / a.d_contrast, a.d_contrast)

        def lin(sx, sy, phi, sh):  # shear . rotate . scale, as make_patch composes them
            cs, sn = math.cos(phi), math.sin(phi)
            return np.array([[1, sh], [0, 1]]) @ np.array([[cs, sn], [-sn, cs]]) @ np.diag([sx, sy])
        return lin(sx, sy, phi, sh), lin(sx_, sy, phi_, sh_), ty_, (c, b), (c_, b_)

    def _cut(self, img: torch.Tensor, centre, A, hh: int, ww: int, ty: float, exact: bool):
        """Crop (1, 1, hh, ww) whose centre pixel is source point ``centre`` under forward map A."""
        H, W = img.shape[-2:]
        if exact:
            x0, y0 = int(centre[0]) - ww // 2, int(centre[1]) - hh // 2
            pad = (max(0, -x0), max(0, x0 + ww - W), max(0, -y0), max(0, y0 + hh - H))
            src = F.pad(img, pad) if any(pad) else img
            x0 += pad[0]
            y0 += pad[2]
            return src[:, :, y0:y0 + hh, x0:x0 + ww]
        Ai = np.linalg.inv(A)
        jj, ii = np.meshgrid(np.arange(ww) - ww // 2, np.arange(hh) - hh // 2)
        pts = np.stack([jj.ravel(), ii.ravel()])
        src = Ai @ pts + np.array([[centre[0]], [centre[1] + ty]])
        gx = src[0] * (2.0 / (W - 1)) - 1
        gy = src[1] * (2.0 / (H - 1)) - 1
        grid = torch.from_numpy(np.stack([gx, gy], -1).reshape(1, hh, ww, 2).astype(np.float32))
        return F.grid_sample(img, grid, mode="bilinear", padding_mode="zeros", align_corners=True)

    def sample(self, rng: np.random.Generator, n_crops: int, take: tuple | None = None) -> CropBatch:
        """Draw ``n_crops`` crop pairs and their examples (``rng`` drives everything: reproducible).

        ``take=(start, stop)``: return only crops ``start..stop-1`` of those
        ``n_crops`` (renumbered from 0).  Every crop's random numbers are still
        drawn, so the crops taken are exactly those of the full draw, and the
        ranks of a distributed step, each taking its own range of one draw,
        together hold exactly the batch one process would get; crops outside
        the range are not cut.
        """
        start, stop = (0, n_crops) if take is None else take
        if not 0 <= start < stop <= n_crops:
            raise InputError(f"take must be a non-empty range within 0..{n_crops}, got {take}")
        r, h, w, wr = self.r, self.h, self.w, self.wr
        Hc, Wc, Wrc = h + 2 * r, w + 2 * r, wr + 2 * r
        exact = not self.subpixel and not self.augmenting
        lefts, rights, crops, qls, qps, qns, srcs = [], [], [], [], [], [], []
        K = self.negatives
        b = 0
        while b < n_crops:
            pi = int(rng.choice(len(self.keys), p=self.prob))
            valid, disp, xs, ys = self.gt[pi]
            L, R = self.imgs[pi]
            H, W = L.shape[-2:]
            k = int(rng.integers(len(xs)))
            xa, ya = int(xs[k]), int(ys[k])
            da = float(disp[ya, xa])
            aug = self.pair_aug[pi]
            p_hi, n_lo, n_hi = self.pair_off[pi]
            A, B, ty, (cl, bl), (cr, br) = self._draw_warp(rng, aug)
            xra = xa - int(math.floor(da + 0.5))  # right crop centre: the anchor's (rounded) match
            # Candidate GT pixels: a source window covering the left crop under any allowed warp.
            ext = int(math.ceil(max(h, w) * 0.75)) + 2 if aug is not None else 0
            hy, hx = (h // 2 + ext), (w // 2 + ext)
            y0, y1 = max(ya - hy, 0), min(ya + hy + 1, H)
            x0, x1 = max(xa - hx, 0), min(xa + hx + 1, W)
            wy, wx = np.nonzero(valid[y0:y1, x0:x1])
            py, px = (wy + y0).astype(np.float64), (wx + x0).astype(np.float64)
            d = disp[py.astype(int), px.astype(int)].astype(np.float64)
            if not self.subpixel:
                d = np.floor(d + 0.5)
            m = len(px)
            if m == 0:
                continue
            if self.subpixel:
                op = rng.uniform(-p_hi, p_hi, m)
                on = rng.uniform(n_lo, n_hi, (m, K))
            else:
                op = rng.integers(-int(p_hi), int(p_hi) + 1, m).astype(np.float64)
                on = rng.integers(int(n_lo), int(n_hi) + 1, (m, K)).astype(np.float64)
            on = np.where(rng.random((m, K)) < 0.5, -on, on)
            xp = px - d + op
            xn = px[:, None] - d[:, None] + on
            # Feature-map positions (x, y): crop centre pixel at (w // 2, h // 2) in the feature map.
            qlx, qly = A @ np.stack([px - xa, py - ya])
            qlx, qly = qlx + w // 2, qly + h // 2
            # The right crop is cut ty rows lower (d_vtrans): the right patches sit at the left
            # pixel's crop row, so they come from image row py + ty, as the released make_patch
            # shifts the right patch by trans_[2] (imperfect rectification).
            qpx, qpy = B @ np.stack([xp - xra, py - ya])
            qpx, qpy = qpx + wr // 2, qpy + h // 2
            qn = np.einsum("ij,jmk->imk", B, np.stack([xn - xra, np.broadcast_to((py - ya)[:, None], xn.shape)]))
            qnx, qny = qn[0] + wr // 2, qn[1] + h // 2
            lo = float(r)
            ok = ((px >= lo) & (px <= W - 1 - r) & (py >= lo) & (py <= H - 1 - r)
                  & (xp >= lo) & (xp <= W - 1 - r) & (xn >= lo).all(1) & (xn <= W - 1 - r).all(1)
                  & (qlx >= 0) & (qlx <= w - 1) & (qly >= 0) & (qly <= h - 1)
                  & (qpx >= 0) & (qpx <= wr - 1) & (qpy >= 0) & (qpy <= h - 1)
                  & (qnx >= 0).all(1) & (qnx <= wr - 1).all(1) & (qny >= 0).all(1) & (qny <= h - 1).all(1))
            idx = np.flatnonzero(ok)
            if len(idx) == 0:
                continue
            if len(idx) > self.per_crop:
                idx = np.sort(rng.choice(idx, self.per_crop, replace=False))
            if not start <= b < stop:  # another rank's crop: its random numbers are drawn, nothing is cut
                b += 1
                continue
            lc = self._cut(L, (xa, ya), A, Hc, Wc, 0.0, exact) * cl + bl
            rc = self._cut(R, (xra, ya), B, Hc, Wrc, ty, exact) * cr + br
            lefts.append(lc)
            rights.append(rc)
            crops.append(np.full(len(idx), b - start, np.int64))
            qls.append(np.stack([qlx[idx], qly[idx]], -1))
            qps.append(np.stack([qpx[idx], qpy[idx]], -1))
            qns.append(np.stack([qnx[idx], qny[idx]], -1))
            srcs.append((np.full(len(idx), pi), px[idx], py[idx], xp[idx], xn[idx]))
            b += 1
        t = lambda a: torch.from_numpy(np.concatenate(a)).to(torch.float32)  # noqa: E731
        return CropBatch(left=torch.cat(lefts).contiguous(), right=torch.cat(rights).contiguous(),
                         crop=torch.from_numpy(np.concatenate(crops)), ql=t(qls), qp=t(qps), qn=t(qns),
                         exact=exact, src=dict(zip(("pair", "x", "y", "x_pos", "x_neg"),
                                                   (np.concatenate(a) for a in zip(*srcs)))))


def crop_outputs(model, batch: CropBatch, device):
    """Head outputs (pos (N,), neg (N, K)) of a crop batch: one conv pass per crop, features gathered."""
    fl = model.raw_features(batch.left.to(device))
    fr = model.raw_features(batch.right.to(device))
    crop = batch.crop.to(device)
    K = batch.qn.shape[1]
    gl = model.finish(gather(fl, crop, batch.ql.to(device), batch.exact), -1)
    gp = model.finish(gather(fr, crop, batch.qp.to(device), batch.exact), -1)
    gn = model.finish(gather(fr, crop[:, None].expand(-1, K), batch.qn.to(device), batch.exact), -1)
    out_p = model.head(gl, gp)
    out_n = model.head(gl[:, None, :].expand(-1, K, -1), gn)
    return out_p, out_n


def crop_loss(model, batch: CropBatch, device) -> torch.Tensor:
    """The architecture's loss over every (positive, negative_k) pair of the batch."""
    out_p, out_n = crop_outputs(model, batch, device)
    K = out_n.shape[1]
    if out_p.dim() == 2:  # paper logits (N, 2) / (N, K, 2)
        return model.loss(out_p.repeat_interleave(K, 0) if K > 1 else out_p, out_n.reshape(-1, 2))
    return model.loss(out_p[:, None].expand(-1, K).reshape(-1), out_n.reshape(-1))
