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

Every one of them is a :class:`~.base.MatchingCost` (one registry:
:func:`cost_classes`) and has

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
``scratch_bytes(H, W, rows=None)``
    upper bound of the device bytes a call allocates besides the H x W volume
    (the networks: in bands of ``rows`` volume rows, None: ``band_rows(H, W)``,
    the most a band takes; census ignores ``rows``).
``band_rows(H, W)``
    the most volume rows one band takes (census: H, it does not band).
``__call__(I_L, I_R, D, out=None, progress=None, stats=None, scratch=None, rows=None) -> device buffer``
    the volume on the device (into ``out`` when given; the networks in bands
    of ``rows`` rows, fewer than ``band_rows`` when the caller's memory is tight);
    ``progress(done, D)`` is called as disparities or bands complete;
    ``scratch``, a device buffer lent for the call (the stereo method lends
    SGM's output volume, first written after the cost): the networks carve
    their conv maps from it instead of holding buffers of their own.
``lent_scratch_bytes(H, W, lent, rows=None)``
    of ``scratch_bytes(H, W, rows)``, the bytes a loan of ``lent`` bytes surely
    holds (the memory planner counts the rest).
``to_host(I_L, I_R, D, max_bytes=None, progress=None, stats=None, rows=None) -> ndarray``
    the volume in host memory, using at most ``max_bytes`` of device memory
    for it at a time where the cost can band (census computes then copies).
``flops(H_img, W_img, D) -> dict``
    arithmetic of one volume (``total`` and its parts).
``release_buffers()``
    frees the scratch kept between calls (the networks keep their conv
    stack's maps: first writes to fresh buffers cost page mapping on CPUs).

Images may be on any intensity scale: the networks standardise each image,
census only compares intensities.  :func:`make_cost` picks the class from
``Weights.architecture`` through the registry; nothing after it branches on
the architecture.
"""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

from ..errors import WeightsError
from ..weights import Weights
from .base import registered


def cost_classes() -> dict:
    """key ("census" or a ``Weights.architecture``) -> cost class: every
    :class:`~.base.MatchingCost` subclass of the modules of this package."""
    for info in pkgutil.iter_modules([str(Path(__file__).parent)]):
        importlib.import_module(f"{__package__}.{info.name}")
    return registered()


def make_cost(ctx, weights, half: bool = False, tiles: dict | None = None):
    """The cost stage for ``weights`` (a :class:`Weights`) or ``"census"``."""
    if isinstance(weights, str) and weights == "census":
        key = "census"
    elif isinstance(weights, Weights):
        key = weights.architecture
    else:
        raise WeightsError(f"make_cost needs Weights or 'census', got {type(weights).__name__}")
    classes = cost_classes()
    if key not in classes:
        raise WeightsError(f"no cost stage for architecture {key!r}")
    return classes[key].build(ctx, weights, half=half, tiles=tiles)
