"""Reference of the matching cost C_CNN: the network run patch by patch.

This is the paper's definition ("Matching cost"), written for clarity:

    C_CNN(p, d) = f_neg(< P^L_9x9(p), P^R_9x9(p - d) >)

For every volume cell (d, y, x) the left patch is centred at image pixel
(x + m, y + m) and the right one at (x + m - d, y + m), m = 4 for 9x9 patches;
both patches go through the tied layers L1..L3 (valid convolutions with ReLU,
which reduce a 9x9 patch to one feature vector), the two vectors are
concatenated and go through L4..L8 (ReLU after all but L8); the cost is the
softmax probability of the bad-match class 0.  Cells with x - d < 0 (the right
patch would leave the image) are NaN.

:func:`cost_volume` computes in float64 with numpy; the tower output of a
patch does not depend on which patch it is paired with, so it is computed once
per patch, and the head runs on the full concatenation (no L4 split).

:func:`fst_cost_volume` is MC-CNN-fst's cost: the tower without the ReLU
after its last layer, each feature vector divided by sqrt(|f|^2 + 1e-5),
then C(d, y, x) = -f_L(x, y) . f_R(x - d, y) (an explicit loop over d).
:func:`cost_volume` covers acrt too: its head ends in 1 output and a sigmoid.

:func:`cost_volume_torch` is the same computation the way the OpenCL stage
does it (L1..L3 fully convolutionally, L4 split, per-disparity head), with
``mccnn_cl.train.model.MCCNN`` in float32; used by the tests and ``bench/``.
"""

from __future__ import annotations

import numpy as np

from ..costs.network import normalise
from ..weights import Weights


def _patches(img: np.ndarray, P: int) -> np.ndarray:
    """All P x P patches of an H x W x C image: (H-P+1, W-P+1, C, P, P)."""
    win = np.lib.stride_tricks.sliding_window_view(img, (P, P), axis=(0, 1))
    return win  # (h, w, C, P, P), a view


def tower(weights: Weights, patches: np.ndarray) -> np.ndarray:
    """The conv layers on patches (N, C, P, P) -> feature vectors (N, maps), float64:
    ReLU after each layer, the last only when ``weights.relu_after_last_conv``."""
    x = np.asarray(patches, dtype=np.float64)
    n = x.shape[0]
    last = len(weights.conv) - 1
    for i, (W, b) in enumerate(weights.conv):
        cout, cin, k, _ = W.shape
        win = np.lib.stride_tricks.sliding_window_view(x, (k, k), axis=(2, 3))  # (N, C, s, s, k, k)
        s = win.shape[2]
        cols = win.transpose(0, 2, 3, 1, 4, 5).reshape(n * s * s, cin * k * k)
        y = cols @ W.reshape(cout, cin * k * k).astype(np.float64).T + b.astype(np.float64)
        if i < last or weights.relu_after_last_conv:
            y = np.maximum(y, 0.0)
        x = y.reshape(n, s, s, cout).transpose(0, 3, 1, 2)
    return x.reshape(n, -1)


def head(weights: Weights, fl: np.ndarray, fr: np.ndarray) -> np.ndarray:
    """L4..L8 and softmax on pairs of feature vectors (N, maps) x2 -> P(bad match) (N,).
    A last layer of 1 output (acrt) goes through a sigmoid instead."""
    x = np.concatenate([fl, fr], axis=1)
    for i, (W, b) in enumerate(weights.fc):
        x = x @ W.astype(np.float64).T + b.astype(np.float64)
        if i < len(weights.fc) - 1:
            x = np.maximum(x, 0.0)
    if x.shape[1] == 1:
        return 1.0 / (1.0 + np.exp(-x[:, 0]))
    z = x - x.max(axis=1, keepdims=True)  # stable softmax
    e = np.exp(z)
    return e[:, 0] / e.sum(axis=1)


def cost_volume(weights: Weights, left, right, max_disparity: int, min_disparity: int = 0) -> np.ndarray:
    """C_CNN as float32 ``[D][H_img-P+1][W_img-P+1]``, NaN where x - d < 0
    (level k is disparity ``min_disparity + k``; NaN also where x - d >= W).

    ``left``/``right``: 2-D gray images (normalised here, like the stage does).
    """
    P = weights.patch_size
    L = normalise(left).astype(np.float64)
    R = normalise(right).astype(np.float64)
    if L.ndim == 2:
        L, R = L[:, :, None], R[:, :, None]
    pl, pr = _patches(L, P), _patches(R, P)
    h, w = pl.shape[:2]
    fl = tower(weights, pl.reshape(h * w, *pl.shape[2:])).reshape(h, w, -1)
    fr = tower(weights, pr.reshape(h * w, *pr.shape[2:])).reshape(h, w, -1)
    D, M = int(max_disparity), int(min_disparity)
    out = np.full((D, h, w), np.nan, np.float32)
    for k, x0, x1 in _valid_columns(D, M, w):
        # valid cells x = x0 .. x1-1: left patch at x, right patch at x - d
        d = M + k
        a = fl[:, x0:x1, :].reshape(-1, fl.shape[2])
        b = fr[:, x0 - d:x1 - d, :].reshape(-1, fr.shape[2])
        out[k, :, x0:x1] = head(weights, a, b).reshape(h, x1 - x0)
    return out


def _valid_columns(D, M, w):
    """(k, x0, x1) for each level k = d - M with valid cells x0 <= x < x1 (0 <= x - d < w)."""
    for k in range(D):
        d = M + k
        x0, x1 = max(d, 0), min(w, w + d)
        if x1 > x0:
            yield k, x0, x1


def conv_layer(x, W, b, relu: bool = True) -> np.ndarray:
    """One conv layer of a channel-last map, float64, as the conv stack's kernels compute it:
    the valid k x k convolution of ``x`` [h][w][cin] with ``W`` [cout][cin][k][k], plus ``b``,
    then ReLU when ``relu``; returns [(h - k + 1) * (w - k + 1)][cout]."""
    k = W.shape[2]
    h, w = x.shape[:2]
    out = np.zeros((h - k + 1, w - k + 1, W.shape[0]))
    for ky in range(k):
        for kx in range(k):
            out += x[ky:ky + h - k + 1, kx:kx + w - k + 1].astype(np.float64) @ np.asarray(
                W[:, :, ky, kx], np.float64).T
    out = out + np.asarray(b, np.float64)
    return (np.maximum(out, 0) if relu else out).reshape(-1, W.shape[0])


def image_features(weights: Weights, img) -> np.ndarray:
    """The tower at every patch of a standardised image: (H-P+1, W-P+1, maps), float64."""
    P = weights.patch_size
    I = normalise(img).astype(np.float64)
    if I.ndim == 2:
        I = I[:, :, None]
    p = _patches(I, P)
    h, w = p.shape[:2]
    return tower(weights, p.reshape(h * w, *p.shape[2:])).reshape(h, w, -1)


def fst_features(weights: Weights, img) -> np.ndarray:
    """fst's normalised features: f / sqrt(sum f^2 + 1e-5) per pixel (released code's Normalize2)."""
    f = image_features(weights, img)
    return f / np.sqrt((f * f).sum(axis=2, keepdims=True) + 1e-5)


def fst_cost_volume(weights: Weights, left, right, max_disparity: int, min_disparity: int = 0) -> np.ndarray:
    """MC-CNN-fst's volume, float32 ``[D][H_img-P+1][W_img-P+1]``:
    C(k, y, x) = -f_L(x, y) . f_R(x - d, y) at d = min_disparity + k, NaN
    unless 0 <= x - d < W."""
    fl, fr = fst_features(weights, left), fst_features(weights, right)
    h, w = fl.shape[:2]
    D, M = int(max_disparity), int(min_disparity)
    out = np.full((D, h, w), np.nan, np.float32)
    for k, x0, x1 in _valid_columns(D, M, w):
        d = M + k
        out[k, :, x0:x1] = -np.einsum("yxk,yxk->yx", fl[:, x0:x1], fr[:, x0 - d:x1 - d])
    return out


def cost_volume_torch(weights: Weights, left, right, max_disparity: int, model=None) -> np.ndarray:
    """The same volume computed in torch (float32) the way the OpenCL stage does.

    L1..L3 of ``MCCNN.from_weights(weights)`` fully convolutionally on each
    image, L4 split into ``A = W4a f_L + b4`` and ``B = W4b f_R`` once per
    pixel, then per disparity ``ReLU(A(p) + B(p - d))`` through L5..L8 and the
    softmax, batched over all valid pixels.  ``model``: an existing MCCNN to
    reuse (for benchmarks).
    """
    import torch

    from ..train.model import MCCNN

    m = model if model is not None else MCCNN.from_weights(weights)
    maps = weights.feature_maps
    L = torch.from_numpy(normalise(left))[None, None]
    R = torch.from_numpy(normalise(right))[None, None]
    D = int(max_disparity)
    with torch.no_grad():
        fl = m.features(L)[0].permute(1, 2, 0)  # (h, w, maps)
        fr = m.features(R)[0].permute(1, 2, 0)
        h, w = fl.shape[:2]
        W4, b4 = m.fcs[0].weight, m.fcs[0].bias
        A = fl @ W4[:, :maps].T + b4
        B = fr @ W4[:, maps:].T
        out = torch.full((D, h, w), float("nan"))
        for d in range(min(D, w)):
            x = torch.relu(A[:, d:] + B[:, :w - d])
            for i, fc in enumerate(m.fcs[1:]):
                x = fc(x)
                if i < len(m.fcs) - 2:
                    x = torch.relu(x)
            out[d, :, d:] = torch.softmax(x, dim=-1)[..., 0]
    return out.numpy()
