"""Helpers shared by several test modules (test modules import from here, never from each other)."""

import numpy as np


def invalid_mask(D, H, W):
    d = np.arange(D)[:, None, None]
    x = np.arange(W)[None, None, :]
    return np.broadcast_to(x < d, (D, H, W))


def random_volume(rng, D, H, W, scale=1.0):
    c = (scale * rng.random((D, H, W))).astype(np.float32)
    c[invalid_mask(D, H, W)] = np.nan
    return c


def blocky_image(rng, H, W, block=3, noise=0.02):
    """Piecewise-constant image with a little noise: arms of all lengths."""
    img = np.repeat(np.repeat(rng.random((H // block + 1, W // block + 1)), block, 0), block, 1)[:H, :W]
    return (img + noise * rng.random((H, W))).astype(np.float32)


def ad_volume(img_l, img_r, D):
    H, W = img_l.shape
    c = np.full((D, H, W), np.nan, np.float32)
    for d in range(D):
        c[d, :, d:] = np.abs(img_l[:, d:] - img_r[:, :W - d])
    return c
