"""Conventions the stages and their numpy references share: the left-right
check's labels and the mismatch fill's 16 directions (paper, "Refinement").
Production code (:mod:`mccnn_cl.stages`) and the numpy twins
(:mod:`mccnn_cl.reference`) both import them from here, so neither imports
the other."""

from __future__ import annotations

import numpy as np

CORRECT, MISMATCH, OCCLUSION = 0, 1, 2

# The 16 directions of the mismatch fill.  Paper default ("paper"): the 16
# directions of Hirschmüller's SGM, integer steps walked one step at a time
# (k * (dx, dy)), so (2, 1) visits every second column.  Released code
# ("code"): the 8 compass directions plus the 8 in between as half-pixel
# steps, positions rounded to the nearest pixel (halves away from zero).
DIRECTIONS = {
    "paper": np.array([
        (1, 0), (2, 1), (1, 1), (1, 2), (0, 1), (-1, 2), (-1, 1), (-2, 1),
        (-1, 0), (-2, -1), (-1, -1), (-1, -2), (0, -1), (1, -2), (1, -1), (2, -1),
    ], dtype=np.float32),
    "code": np.array([
        (1, 0), (1, 0.5), (1, 1), (0.5, 1), (0, 1), (-0.5, 1), (-1, 1), (-1, 0.5),
        (-1, 0), (-1, -0.5), (-1, -1), (-0.5, -1), (0, -1), (0.5, -1), (1, -1), (1, -0.5),
    ], dtype=np.float32),
}
