"""Refinement (paper, "Refinement"): ``kernels/refine.cl``.

* :class:`Enlarge` - D_SE (cropped domain) to the input image's size, border
  disparities copied outwards.
* :class:`MedianFilter` - size x size median (default 5), clamp-to-edge.
* :class:`BilateralFilter` - the paper's bilateral filter guided by the LEFT
  IMAGE (``guide="image"``, tau on the image's [0, 1] scale: pass
  tau_BF / 255) or the released code's variant guided by the disparity map
  itself (``guide="disparity"``, tau in pixels).

Numpy twins: :mod:`mccnn_cl.reference.disparity` (``enlarge``,
``median_filter``, ``bilateral``).
"""

from __future__ import annotations

import math

import numpy as np

from ..opencl.context import launch

_F32 = np.dtype(np.float32).itemsize


def bilateral_radius(sigma: float) -> int:
    """Default window half-side: ceil(3 sigma) (17 px for sigma = 5.656), as the
    released code's Gaussian kernel; the window is clipped to the image."""
    return max(1, int(math.ceil(3.0 * float(sigma))))


def gaussian_taps(sigma: float, radius: int) -> np.ndarray:
    """g1(k) = exp(-k^2 / (2 sigma^2)), k = -radius..radius (unnormalised, float32)."""
    k = np.arange(-radius, radius + 1, dtype=np.float64)
    return np.exp(-k * k / (2.0 * float(sigma) ** 2)).astype(np.float32)


class Enlarge:
    """Copies an H x W map into an Ho x Wo one at offset ``margin``, replicating
    the border rows and columns."""

    def __init__(self, ctx):
        self.ctx = ctx
        self.kernel = ctx.kernel("refine.cl", "refine_enlarge", MEDIAN_SIZE=5)

    def __call__(self, d_disp, H, W, Ho, Wo, margin, out=None):
        if out is None:
            out = self.ctx.empty(Ho * Wo * _F32, "enlarged disparity")
        launch(self.ctx, "enlarge", self.kernel, (Wo, Ho), d_disp, out, np.int32(H), np.int32(W),
               np.int32(Ho), np.int32(Wo), np.int32(margin))
        return out


def batcher_pairs(n: int) -> list:
    """Compare-exchange steps (i, j), i < j, of Batcher's odd-even merge sort
    of ``n`` (a power of two) values: after them v is sorted ascending."""
    pairs = []
    p = 1
    while p < n:
        k = p
        while k >= 1:
            for j in range(k % p, n - k, 2 * k):
                for i in range(min(k, n - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    return pairs


def median_network(count: int) -> list:
    """Compare-exchange steps (i, j) that leave the middle value of ``count``
    (odd) values in v[count // 2]: Batcher's sorting network for the next power
    of two, the steps touching the padding (+inf there: no-ops) removed, then
    only the steps the middle output depends on kept (walking backwards).
    For 25 values (the 5 x 5 median) 113 steps.  Checked for every 0/1 input
    by tests/test_refine.py (the 0-1 principle)."""
    size = 1
    while size < count:
        size *= 2
    steps = [(i, j) for i, j in batcher_pairs(size) if j < count]
    needed, kept = {count // 2}, []
    for i, j in reversed(steps):
        if i in needed or j in needed:
            kept.append((i, j))
            needed |= {i, j}
    return kept[::-1]


#: Largest median window side served by the vector kernel (its network is
#: checked exhaustively for 3 x 3 and 5 x 5); larger windows use the sorting kernel.
MEDIAN_VECTOR_MAX = 5
#: Largest median window side: the sorting kernel keeps MEDIAN_SIZE^2 floats
#: per work-item in a private array (4 KiB at 31 x 31).
MEDIAN_MAX_SIZE = 31
#: Work-group width of the sorting kernel.  CPU runtimes (PoCL) may lay a
#: whole work-group's private arrays on one thread's stack; the runtime's own
#: choice (up to 4096 work-items: 256 x 256 images) overflowed it and killed
#: the process (SIGSEGV) from 23 x 23 on.  16 work-items x 4 KiB stays small.
MEDIAN_GROUP = 16


class MedianFilter:
    """size x size median filter (``size`` odd; compiled per size).  Windows up
    to 5 x 5 run the vector kernel (16 pixels per work-item through a
    selection network, ~25x faster on PoCL), larger ones the per-pixel
    insertion sort; both give the same values."""

    def __init__(self, ctx, size: int = 5, vector: bool | None = None):
        if size < 1 or size % 2 == 0 or size > MEDIAN_MAX_SIZE:
            raise ValueError(f"median size must be a positive odd number <= {MEDIAN_MAX_SIZE}, not {size}")
        self.ctx = ctx
        self.size = int(size)
        self.vector = self.size <= MEDIAN_VECTOR_MAX if vector is None else bool(vector)
        if self.vector:
            if self.size > MEDIAN_VECTOR_MAX:
                raise ValueError(f"the vector median serves sizes up to {MEDIAN_VECTOR_MAX}, not {size}")
            net = "".join(f"MEDIAN_CE({i},{j})" for i, j in median_network(self.size ** 2))
            self.kernel = ctx.kernel("refine.cl", "refine_median16", MEDIAN_SIZE=self.size, MEDIAN_NET=net)
        else:
            self.kernel = ctx.kernel("refine.cl", "refine_median", MEDIAN_SIZE=self.size)

    def __call__(self, d_disp, H, W, out=None):
        if out is None:
            out = self.ctx.empty(H * W * _F32, "median-filtered disparity")
        if self.vector:
            launch(self.ctx, "median filter", self.kernel, (-(-W // 16), H), d_disp, out, np.int32(H), np.int32(W))
        else:  # a small explicit work-group: see MEDIAN_GROUP
            launch(self.ctx, "median filter", self.kernel, (-(-W // MEDIAN_GROUP) * MEDIAN_GROUP, H),
                   d_disp, out, np.int32(H), np.int32(W), local_size=(MEDIAN_GROUP, 1))
        return out


class BilateralFilter:
    """D_BF(p) = sum_q D(q) g(|p-q|) 1{|G(p) - G(q)| < tau} / W(p).

    ``d_guide`` is the left image (paper) or ``d_disp`` itself (released
    code's variant); ``radius`` defaults to :func:`bilateral_radius`.
    """

    def __init__(self, ctx):
        self.ctx = ctx
        self.kernel = ctx.kernel("refine.cl", "refine_bilateral", MEDIAN_SIZE=5)
        self._taps = {}  # (sigma, radius) -> the Gaussian tap table on the device

    def release_buffers(self) -> None:
        """Free the tap tables kept between calls (a few KB each; the next call
        makes its table again).  Work already queued on them still runs (OpenCL
        keeps a released buffer until its commands complete)."""
        for buf in self._taps.values():
            buf.release()
        self._taps.clear()

    def __call__(self, d_disp, d_guide, H, W, sigma, tau, radius=None, out=None):
        radius = bilateral_radius(sigma) if radius is None else int(radius)
        # taps beyond the map never count (the window is clipped to it): a
        # radius past max(H, W) gives the same sums, with a bounded tap buffer
        radius = min(radius, max(int(H), int(W)))
        key = (float(sigma), radius)
        if key not in self._taps:
            self._taps[key] = self.ctx.to_device(gaussian_taps(sigma, radius))
        if out is None:
            out = self.ctx.empty(H * W * _F32, "D_BF")
        launch(self.ctx, "bilateral filter", self.kernel, (-(-W // 16), H), d_disp, d_guide, self._taps[key], out,
               np.int32(H), np.int32(W), np.int32(radius), np.float32(tau))
        return out
