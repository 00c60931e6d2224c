"""Numpy twin of the confidence stage (``kernels/confidence.cl``).

The measure (the executable specification, loops and all): for pixel (x, y)
take its cost curve c(d) = C[d, y, x] over the valid levels
d = 0 .. min(D-1, x) and split it into runs of equal cost.  A run is a
*local minimum* when its neighbours on both sides are higher (the curve's
ends count as higher).  With c1 <= c2 the costs of the two lowest local
minima (c1 is the global minimum, the winner-take-all cost; two separate
runs at the same cost give c2 = c1) and cmax the curve's largest cost,

    confidence = (c2 - c1) / (cmax - c1)

with c2 = cmax when the curve has one local minimum only, and 0 when
cmax = c1 (a flat curve, or one valid level).  This is the peak ratio of
the two best matches on the flipped curve s(d) = cmax - c(d):
1 - s2 / s1.  It is invariant under c -> a c + b (a > 0), like the
winner-take-all itself, so one measure serves census and the paper/acrt
networks ([0, 1]), fst ([-1, 1]) and volumes after SGM (sums of path
costs, offsets and ranges that depend on P1, P2).  Pixels whose
left-right label is not CORRECT get 0.
"""

from __future__ import annotations

import numpy as np

from .disparity import CORRECT


def curve_confidence(c: np.ndarray) -> float:
    """The measure of the module docstring on one curve (float32 values, all valid)."""
    c = np.asarray(c, np.float32)
    n = len(c)
    if n == 0:
        return 0.0
    cmax = c.max()
    c1 = c.min()
    if not cmax > c1:
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
    c2 = minima[1] if len(minima) > 1 else cmax
    # float32 arithmetic as in the kernel
    return float(min(np.float32(1.0), np.float32(c2 - c1) / np.float32(cmax - c1)))


def confidence(C: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Confidence map (float32 H x W, in [0, 1]) of volume ``C`` [D][H][W]
    (float32 or float16; invalid cells d > x are skipped by index) and
    left-right ``labels`` (int32 H x W; not CORRECT -> 0)."""
    D, H, W = C.shape
    C = C.astype(np.float32)
    out = np.zeros((H, W), np.float32)
    for y in range(H):
        for x in range(W):
            if labels[y, x] == CORRECT:
                out[y, x] = curve_confidence(C[:min(D - 1, x) + 1, y, x])
    return out
