"""Per-pixel confidence of the disparity (not in the paper): ``kernels/confidence.cl``.

:class:`Confidence` maps the final cost volume C (the one the winner-take-all
and subpixel enhancement read, float32 or half storage) and the left-right
labels to a float32 H x W map in [0, 1] on the cropped domain:
(c2 - c1) / ((c1 - f) + (c2 - f)) with c1 <= c2 the two lowest *local
minima* of the pixel's cost curve and f the matching cost's lower bound
(:func:`cost_floor`); 0 where the label is not correct.  Local minima, not
the two smallest costs, so that the neighbours of a wide minimum do not
count as a rival match; costs measured from f so that the measure does not
depend on the cost's scale (census and paper/acrt costs in [0, 1], fst's
-cosine in [-1, 1]; SGM and CBCA average, so the final volume keeps the
floor of C_CNN).  Definition, plateaus and edge cases:
:mod:`mccnn_cl.reference.confidence` (the numpy twin).  The pipeline enlarges the map to the image size as the
disparity is (border pixels copied outwards), see ``StereoMatcher.compute``.

In the working frame of a range with M < 0 (:mod:`mccnn_cl.disprange`), whose
volume has padding columns, ``right_width`` and ``first_column`` (as
:class:`~mccnn_cl.stages.disparity.LeftRightCheck`, ``Interpolate`` and
``Subpixel`` take them) keep the padding out of the measure: a cell whose right
pixel is padding (x - d >= right_width) is not part of the curve, and a pixel
x < first_column (left padding) gets 0.
"""

from __future__ import annotations

import numpy as np

from ..opencl.context import launch
from ..errors import InputError

_F32 = np.dtype(np.float32).itemsize


def cost_floor(kind: str) -> float:
    """f for a cost ``kind``: "census" or a network architecture
    (``Weights.architecture``): the ``floor`` of its cost class
    (:func:`mccnn_cl.costs.registry.cost_classes`), the one place it is stated."""
    from ..costs.registry import cost_classes

    classes = cost_classes()
    try:
        return classes[kind].floor
    except KeyError:
        raise InputError(f"no cost floor known for {kind!r}; known: {', '.join(classes)}") from None


class Confidence:
    """``Confidence(ctx, half)(d_cost, d_labels, D, H, W, floor=0.0, out=None, right_width=None,
    first_column=0)`` -> float32 H x W buffer.

    ``right_width``: columns of the real right image (default W, the real pair);
    ``first_column``: the first real left column (default 0); both for the
    working frame of a range with M < 0 (module docstring), where the padding's
    cells are then never part of a curve."""

    def __init__(self, ctx, half: bool = False):
        self.ctx = ctx
        self.kernel = ctx.kernel("confidence.cl", "confidence_curve", VOL_HALF=int(half))

    def __call__(self, d_cost, d_labels, D, H, W, floor=0.0, out=None, right_width=None, first_column=0):
        from .disparity import _right_width

        Wr = _right_width(W, right_width)
        if not 0 <= int(first_column) < W:
            raise InputError(f"first_column must be in [0, {W}), not {first_column}")
        if out is None:
            out = self.ctx.empty(H * W * _F32, "confidence")
        launch(self.ctx, "confidence", self.kernel, (-(-W // 16), H), d_cost, d_labels, out,
               np.int32(D), np.int32(H), np.int32(W), np.float32(floor), np.int32(Wr), np.int32(first_column))
        return out
