"""The matching-cost interface every cost stage implements, and :func:`make_cost`.

A cost stage turns a rectified gray pair into a volume ``[D][H][W]`` on the
cropped domain H = H_img - 2 margin, W = W_img - 2 margin; cell (d, y, x)
compares left image pixel (x + m, y + m) with right pixel (x + m - d, y + m);
cells with x - d < 0 hold NaN; lower is a better match.  Costs:

=================  ============  ===========================================
class              architecture  cost
=================  ============  ===========================================
``CensusCost``     (none)        Hamming distance of 9x9 census / 80, [0, 1]
``PaperCost``      mccnn-paper   softmax P(bad match), [0, 1]
``AcrtCost``       mccnn-acrt    sigmoid output, P(bad match), [0, 1]
``FstCost``        mccnn-fst     -cos(f_L, f_R), [-1, 1]
=================  ============  ===========================================

Every one of them has

``margin``
    m, pixels cropped on each side (the networks' (patch - 1) / 2; census 4).
``half``, ``vdtype``
    float16 volume storage or not, and the volume's numpy dtype.
``local``
    True when a row tile's volume can be computed from the tile's image rows
    alone at the cost of a launch (census); False when the volume is best
    computed once for the whole image (the networks: into host memory when
    the stereo method runs on row tiles).
``floor``
    the cost's lower bound (and so every aggregated volume's, as CBCA and SGM
    take means): 0 for census, paper and acrt, -1 for fst; the confidence
    measures costs from it (:mod:`mccnn_cl.stages.confidence`).
``scratch_bytes(H, W)``
    upper bound of the device bytes a call allocates besides the H x W volume.
``__call__(I_L, I_R, D, out=None, progress=None) -> device buffer``
    the volume on the device (into ``out`` when given);
    ``progress(done, D)`` is called as disparities or bands complete.
``to_host(I_L, I_R, D, max_bytes=None, progress=None) -> ndarray``
    the volume in host memory, using at most ``max_bytes`` of device memory
    for it at a time where the cost can band (census computes then copies).
``flops(H_img, W_img, D) -> dict``
    arithmetic of one volume (``total`` and its parts).
``release_buffers()``
    frees the scratch kept between calls (the networks keep their conv
    stack's maps: first writes to fresh buffers cost page mapping on CPUs).

Images may be on any intensity scale: the networks standardise each image,
census only compares intensities.  :func:`make_cost` picks the class from
``Weights.architecture``; nothing after it branches on the architecture.
"""

from __future__ import annotations

from ..errors import WeightsError
from ..weights import ACRT, FST, PAPER, Weights


def make_cost(ctx, weights, half: bool = False, tiles: dict | None = None):
    """The cost stage for ``weights`` (a :class:`Weights`) or ``"census"``."""
    if isinstance(weights, str) and weights == "census":
        from .census import CensusCost

        return CensusCost(ctx, half=half)
    if not isinstance(weights, Weights):
        raise WeightsError(f"make_cost needs Weights or 'census', got {type(weights).__name__}")
    if weights.architecture == FST:
        from .fst import FstCost

        return FstCost(ctx, weights, tiles=tiles, half=half)
    from .network import AcrtCost, PaperCost

    classes = {PAPER: PaperCost, ACRT: AcrtCost}
    if weights.architecture not in classes:
        raise WeightsError(f"no cost stage for architecture {weights.architecture!r}")
    return classes[weights.architecture](ctx, weights, tiles=tiles, half=half)
