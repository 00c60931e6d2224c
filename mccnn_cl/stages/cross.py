"""Cross arms (paper, "Cross-based cost aggregation") - drives ``kernels/cross.cl``.

:class:`CrossArms` computes, for every pixel of one gray image (float32 in
[0, 1], cropped to the cost volume's H x W), the lengths of its four arms.

* Paper (default): the left arm reaches p_l = p - (k, 0) for k = 1, 2, ... as
  long as |I(p) - I(p_l)| < tau AND k < eta AND p_l is inside the image, and
  stops at the first k that fails; its length is the largest such k (0 if
  none).  Right, up and down arms likewise.  KITTI: tau = 0.0442, eta = 4, so
  arms are at most 3 px.
* Released code (``include_neighbor=True``): the +-1 neighbour is always
  included when inside the image (regardless of tau and eta); the comparison
  is still against the centre pixel and eta is still exclusive.

Storage: bytes in four planes [4][H][W] - plane 0 left, 1 right, 2 up,
3 down, "up" towards smaller y; 4 bytes per pixel.  Planar, so that the
aggregation kernels load 16 arms of one kind with one vector load.
:func:`arms_from_device` / :func:`arms_to_device` convert from / to uint8
[H][W][4], the layout of :func:`mccnn_cl.reference.aggregation.cross_arms`.  Because of the byte
storage eta is limited to 256 (arms <= 255).
"""

from __future__ import annotations

import numpy as np

from ..opencl.context import launch
from ..errors import InputError

#: Largest arm length the uchar4 storage can hold.
ARM_LIMIT = 255


def check_size(H, W, what="image") -> tuple:
    """(H, W) as ints; InputError unless both are >= 1."""
    H, W = int(H), int(W)
    if H < 1 or W < 1:
        raise InputError(f"{what} size must be at least 1 x 1, got {H} x {W}")
    return H, W


def max_arm(eta: int, include_neighbor: bool = False) -> int:
    """Upper bound of every arm length CrossArms produces for ``eta``
    (pass it to :class:`mccnn_cl.stages.cbca.CBCA` as ``max_arm``)."""
    bound = max(int(eta) - 1, 0)
    if include_neighbor:
        bound = max(bound, 1)
    return min(bound, ARM_LIMIT)


class CrossArms:
    """Arm lengths of every pixel of one image; see the module docstring."""

    def __init__(self, ctx):
        self.ctx = ctx
        self.kernel = ctx.kernel("cross.cl", "cross_build")

    def __call__(self, d_img, H, W, tau=0.0442, eta=4, include_neighbor=False, out=None):
        """Enqueue the arms of the H x W float32 image ``d_img``; returns the
        uint8 [4][H][W] buffer (``out`` if given, 4*H*W bytes)."""
        H, W = check_size(H, W)
        eta = int(eta)
        if not 0 <= eta <= ARM_LIMIT + 1:
            raise InputError(f"eta must be in [0, {ARM_LIMIT + 1}] (arms are stored as bytes), got {eta}")
        if out is None:
            out = self.ctx.empty(4 * H * W, "cross arms")
        launch(self.ctx, "cross arms", self.kernel, (W, H), d_img, out, np.int32(H), np.int32(W),
               np.float32(tau), np.int32(eta), np.int32(bool(include_neighbor)))
        return out


def arms_from_device(ctx, d_arms, H, W) -> np.ndarray:
    """Blocking copy of an arms buffer to a uint8 [H][W][4] array."""
    planes = ctx.from_device(d_arms, (4, int(H), int(W)), np.uint8)
    return np.ascontiguousarray(np.moveaxis(planes, 0, 2))


def arms_to_device(ctx, arms) -> object:
    """A device arms buffer ([4][H][W] planes) from a uint8 [H][W][4] array
    (e.g. :func:`mccnn_cl.reference.aggregation.cross_arms`)."""
    arms = np.asarray(arms)
    if arms.ndim != 3 or arms.shape[2] != 4 or arms.dtype != np.uint8:
        raise InputError(f"arms must be uint8 [H][W][4], got {arms.dtype} {arms.shape}")
    return ctx.to_device(np.ascontiguousarray(np.moveaxis(arms, 2, 0)))
