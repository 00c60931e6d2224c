"""Numpy twin of the confidence stage (``kernels/confidence.cl``).

The measure (the executable specification, loops and all): pixel (x, y)'s
cost curve c(d) = C[d, y, x], d = 0 .. min(D-1, x), is split into runs of
equal cost; a run is a *local minimum* when its neighbours on both sides
are higher (the curve's ends count as higher).  c1 <= c2: the two lowest
local minima (c1 = the winner-take-all cost; two separate runs at one cost
give c2 = c1; c2 = the curve's largest cost when it has one local minimum).
With f the matching cost's lower bound (``floor``: 0 for census, paper and
acrt, -1 for fst's -cosine) and c' = c - f,

    confidence = (c2 - c1) / ((c1 - f) + (c2 - f)) = (1 - r) / (1 + r),  r = c1' / c2',

a monotone map of the peak ratio r into [0, 1]; 0 where the denominator is
0 (both minima at the floor) and where the left-right label is not CORRECT.
Local minima, so that the shoulders of one wide minimum are no rival.
Invariant under c -> f + a (c - f), a > 0, and SGM's and CBCA's means keep
the matching cost's floor, so one f per cost serves every network's range
and every stage's volume with nothing to tune.  Unlike (c2 - c1) / (cmax -
c1) it sees how good the best match is (a high c1' lowers it), which ranks
errors better (docs/method.md, "Confidence").
"""

from __future__ import annotations

import numpy as np

from .disparity import CORRECT


def curve_confidence(c: np.ndarray, floor: float = 0.0) -> float:
    """The measure of the module docstring on one curve (float32 values, all valid)."""
    c = np.asarray(c, np.float32)
    n = len(c)
    if n == 0:
        return 0.0
    minima = []
    i = 0
    while i < n:
        j = i
        while j + 1 < n and c[j + 1] == c[i]:
            j += 1
        left_higher = i == 0 or c[i - 1] > c[i]
        right_higher = j == n - 1 or c[j + 1] > c[i]
        if left_higher and right_higher:
            minima.append(c[i])
        i = j + 1
    minima.sort()
    c1 = minima[0]
    c2 = minima[1] if len(minima) > 1 else c.max()
    f = np.float32(floor)
    den = np.float32(np.float32(c1 - f) + np.float32(c2 - f))  # float32 arithmetic as in the kernel
    if not den > 0:
        return 0.0
    return float(min(np.float32(1.0), np.float32(c2 - c1) / den))


def confidence(C: np.ndarray, labels: np.ndarray, floor: float = 0.0, right_width: int | None = None,
               first_column: int = 0) -> np.ndarray:
    """Confidence map (float32 H x W, in [0, 1]) of volume ``C`` [D][H][W]
    (float32 or float16; invalid cells d > x are skipped by index),
    left-right ``labels`` (int32 H x W; not CORRECT -> 0) and the cost's
    lower bound ``floor``.  ``right_width`` (None: W) and ``first_column``
    (0): the working frame of a range with M < 0 (mccnn_cl/disprange.py),
    whose padding is never part of a curve: pixel x's curve is its levels
    d = max(0, x - right_width + 1) .. min(D-1, x) (the right pixel x - d a
    real one), and pixels x < first_column (left padding) get 0."""
    D, H, W = C.shape
    Wr = W if right_width is None else int(right_width)
    C = C.astype(np.float32)
    out = np.zeros((H, W), np.float32)
    for y in range(H):
        for x in range(int(first_column), W):
            if labels[y, x] == CORRECT:
                out[y, x] = curve_confidence(C[max(0, x - Wr + 1):min(D - 1, x) + 1, y, x], floor)
    return out
