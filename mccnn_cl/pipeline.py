"""The stereo method of the paper, end to end: :class:`StereoMatcher`.

``StereoMatcher(...).compute(left, right)`` runs, in the paper's order
(section "Stereo method"; names from the paper)::

    C_CNN    matching cost: the network (cost="cnn") or census (cost="census")
    C_CBCA   cross-based cost aggregation, cbca_iterations times
    C_SGM    semiglobal matching
    C        cross-based cost aggregation again, cbca_iterations_after times
    D_L, D_R winner-take-all, left and right reference, from the same volume C
    labels   left-right check (correct / mismatch / occlusion)
    D_INT    interpolation
    D_SE     subpixel enhancement on C (the volume the WTA used)
    D_E      enlarged to the image size (border disparities copied)
    D_median median filter
    D_BF     bilateral filter  -> the result

Every stage runs on the OpenCL device; host<->device copies happen only at the
edges (images in, disparity map out), and for ``return_intermediates=True``
after each stage (the same code path, buffers copied back).  Stage definitions,
intensity scales and the paper-vs-released-code variants: ``docs/method.md``.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from .opencl.context import BufferPool, ClContext
from .errors import InputError, WeightsError
from .imageops import to_gray  # noqa: F401 (also importable from here)
from .validate import PATCH, check_disparity_range, check_pair  # noqa: F401 (PATCH re-exported)
from .hyperparameters import Hyperparameters, check_settings  # noqa: F401 (Hyperparameters re-exported)
from .costs.registry import make_cost
from .costs.features import normalise
from .stages.cross import CrossArms, max_arm
from .stages.confidence import Confidence
from .stages.disparity import Interpolate, LeftRightCheck, RightReference, Subpixel, WinnerTakeAll
from .stages.refine import BilateralFilter, Enlarge, MedianFilter
from .disprange import RangeFrame, RangeMask, check_min_disparity, choose_range, levels_of
from .weights import Weights

log = logging.getLogger(__name__)

#: Image-sized buffers the method keeps at most (images, cross arms of both
#: references, disparity maps and labels), counted in float32 images: an
#: upper bound used by :meth:`StereoMatcher.memory_plan`.
MAP_BUFFERS = 24
#: Fewest core rows of a tile (fewer would spend most of the work on overlap).
MIN_TILE_ROWS = 16
#: Default ``tile_overlap``: rows of context above and below a tile's core.
TILE_OVERLAP = 64
#: Fewest rows of a network band the planner takes to keep the whole image at
#: once (thinner bands recompute the conv layers' P - 1 rows of context too
#: often: the volume stages run on row tiles instead).
MIN_BAND_ROWS = 16


def _largest(fits, most: int) -> int:
    """The largest r in 1 .. ``most`` with ``fits(r)`` (true up to some r, false
    above: memory grows with r), 0 when none fits."""
    lo, hi = 0, int(most)
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if fits(mid):
            lo = mid
        else:
            hi = mid - 1
    return lo


@dataclass
class MemoryPlan:
    """Device memory use of one :meth:`StereoMatcher.compute` call (bytes).

    ``volume_bytes``: one D x H x W float32 cost volume of the whole image;
    ``volumes``: volumes alive at once (2: the aggregated right reference
    mirrors the left volume in place); ``peak_bytes``: estimated peak of the
    call's device buffers (an upper bound; the matcher's weights,
    ``StereoMatcher.fixed_bytes``, come on top: the plan keeps
    ``peak_bytes + fixed_bytes <= budget``); ``budget``: the ``memory_limit``
    it was planned for; ``tiles``: ``(core_start, core_stop, start, stop)`` row
    ranges of the cost volume's domain (one tile covering every row: the
    whole image at once); ``overlap``: rows of context on each side of a
    core; ``host_bytes``: host memory holding the network's cost volume when
    tiled (0 otherwise); ``tile_budget``: device bytes for the network's
    band volume when the volume goes to the host (``band_rows`` rows); ``tiled``:
    the volume stages run tile by tile (the network's volume through host
    memory), else on the whole image at once; ``band_rows``: volume rows per
    band of the network's cost, chosen so that a band's volume, its feature
    maps and the image-sized buffers fit ``budget`` (fewer than the cost's
    ``band_rows`` under a tight limit; None for census, which does not band).
    """

    volume_bytes: int
    volumes: int
    peak_bytes: int
    budget: int
    tiles: list
    overlap: int
    host_bytes: int
    tile_budget: int
    tiled: bool
    band_rows: int | None = None

    @property
    def largest_volume(self) -> int:
        """Bytes of the largest volume buffer a call makes (one tile's when tiled)."""
        rows = max(c1 for _, c1, _, _ in self.tiles)
        return self.volume_bytes // rows * max(e1 - e0 for _, _, e0, e1 in self.tiles)

    def describe(self) -> str:
        mib = 2 ** 20
        text = (f"cost volume {self.volume_bytes / mib:.0f} MiB, {self.volumes} alive at once; "
                f"planned device peak {self.peak_bytes / mib:.0f} MiB of {self.budget / mib:.0f} MiB")
        if self.tiled:
            cores = [c1 - c0 for c0, c1, _, _ in self.tiles]
            text += (f"; {len(self.tiles)} row tiles of {max(cores)} rows + {self.overlap} overlap"
                     + (f", network volume in host memory ({self.host_bytes / mib:.0f} MiB)"
                        if self.host_bytes else ""))
        if self.band_rows is not None:
            text += f"; network in bands of {self.band_rows} rows"
        return text


@dataclass
class StereoResult:
    """What :meth:`StereoMatcher.compute` returns with ``return_intermediates``.

    ``disparity``: D_BF (float32, the left image's size, pixels).
    ``intermediates``: name -> host array (C_CNN, C_CBCA, C_SGM, C: float32
    [D][H-2m][W-2m], float16 with ``volume_dtype="float16"``; C_R with ``right_reference="aggregated"``: the final
    right-reference volume, mirrored left to right (see
    :class:`mccnn_cl.stages.disparity.RightReference`); D_L, D_R, labels, D_INT: int32 on the cropped domain;
    D_SE: float32 cropped; D_median, D_BF: float32 image size).
    ``timings``: stage -> seconds (queue finished after every stage), keyed by
    the output names above plus ``cross`` (arms), and with
    ``right_reference="aggregated"`` ``right_volume`` (the shifted, mirrored
    C_CBCA: the right reference's first aggregation; only where SGM cannot
    read C_CBCA mirrored itself, i.e. not with the paired sweeps), ``cross_R``,
    ``C_R_SGM``, ``C_R`` (the later stages for the right reference).
    ``margin``: m, the offset of the cropped domain in the image.
    ``disparity_range``: ``(min, max)``, the disparities searched (inclusive;
    chosen per pair with ``max_disparity="auto"``), and ``auto``: what the
    automatic range's coarse passes found (:func:`mccnn_cl.disprange.choose_range`),
    None otherwise.  With a minimum disparity M != 0 every intermediate is
    in the image's frame as with M = 0 (volumes ``[D][H-2m][W-2m]``, level k
    = disparity M + k, NaN where the right pixel is outside the image; maps
    in disparities).
    ``plan``: the :class:`MemoryPlan` followed; ``peak_device_bytes``: the
    peak of the device buffers the run held beyond those alive when it began
    (measured: every buffer made through the context, freed when released or
    collected).  With ``compute(..., confidence=True)``: ``confidence``, the
    per-pixel confidence in [0, 1] of :class:`mccnn_cl.stages.confidence.Confidence`
    (0 where the left-right check did not label the pixel correct), and
    ``labels``, the left-right labels (int32 0 correct / 1 mismatch / 2
    occlusion), both the image's size with the border filled as D_E's
    (the cropped domain's edge copied outwards); None otherwise.  When the plan
    is tiled, volumes are not kept (only maps, assembled from the tiles'
    cores) and a stage's time is the sum over tiles (``C_CNN_upload``: the
    host-to-device copies of the network's volume).
    """

    disparity: np.ndarray
    intermediates: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    margin: int = 4
    plan: MemoryPlan | None = None
    peak_device_bytes: int = 0
    confidence: np.ndarray | None = None
    labels: np.ndarray | None = None
    disparity_range: tuple | None = None
    auto: dict | None = None


def _resolve_weights(spec) -> Weights:
    """Weights for ``cost="cnn"`` through :func:`mccnn_cl.models.resolve` (None: the shipped network)."""
    from .models import resolve

    try:
        return resolve(spec)
    except WeightsError as exc:
        if spec is None:
            raise WeightsError(f"no trained weights available ({exc}); pass weights=<path or "
                               "Weights> or use cost='census'") from exc
        raise


class StereoMatcher:
    """MC-CNN stereo matcher (the paper's stereo method on the OpenCL device).

    Parameters
    ----------
    weights : None, name, path or Weights
        The network for ``cost="cnn"`` (:func:`mccnn_cl.models.resolve`:
        None the shipped model, a shipped name, .npz, .t7, .pt); any
        architecture (paper, fst, acrt).  Its ``Weights.stereo`` settings are
        applied first, the ``hyperparameters`` given here override them;
        :attr:`params` shows the result.
    max_disparity : int or "auto"
        D, the number of disparity levels (disparities M .. M+D-1); 228 =
        KITTI.  "auto": chosen per pair by coarse passes
        (:func:`mccnn_cl.disprange.choose_range`).
    device : None, str or ClContext
        OpenCL device spec (see :func:`mccnn_cl.opencl.context.select_device`) or a context.
    cost : "cnn" or "census"
        The matching cost: the network, or a 9 x 9 census transform (no weights).
    progress : bool
        Show a tqdm bar while the cost volume is computed.
    memory_limit : None or int
        Bytes of device memory the matcher may hold at once: its weights,
        what it keeps between calls and a call's buffers, with
        ``max_disparity="auto"`` the coarse passes' too (default: 3/4 of the
        device's global memory).  The network's bands are made thinner to fit
        it; when the whole image's cost volumes still do not fit it, or one
        volume exceeds the device's max allocation, the volume stages run on
        row tiles (see :meth:`memory_plan`).
    volume_dtype : "float32" or "float16"
        Storage of the cost volumes on the device (arithmetic is float32
        either way): "float16" halves their memory and traffic at the cost
        of rounding every stored cost to 11 significant bits (docs/method.md,
        "Half-precision volumes": accuracy and speed measured).
    tile_overlap : int
        Rows of context above and below each tile's core rows (default
        ``TILE_OVERLAP``).  The network and cross-based aggregation are exact
        within it; SGM's vertical paths and interpolation's search are cut at
        the tile's edge (see docs/method.md, "Large images").
    min_disparity : int
        M, the smallest disparity searched (negative allowed; as OpenCV's
        ``minDisparity``).  0 by default.
    **hyperparameters
        Overrides of :class:`Hyperparameters` fields by name.
    """

    def __init__(self, weights=None, max_disparity: int = 228, device=None, cost: str = "cnn",
                 progress: bool = False, memory_limit: int | None = None,
                 tile_overlap: int = TILE_OVERLAP, volume_dtype: str = "float32", min_disparity: int = 0,
                 **hyperparameters):
        unknown = sorted(set(hyperparameters) - set(Hyperparameters.names()))
        if unknown:
            raise TypeError(f"unknown hyperparameter(s) {', '.join(unknown)}; valid names: "
                            + ", ".join(Hyperparameters.names()))
        if cost not in ("cnn", "census"):
            raise InputError(f"cost must be 'cnn' or 'census', not {cost!r}")
        if cost == "census" and weights is not None:
            raise InputError("weights are for cost='cnn'; cost='census' uses no network (drop weights= or the cost)")
        # the network's own settings (Weights.stereo), then the caller's explicit overrides
        self.weights = _resolve_weights(weights) if cost == "cnn" else None
        if self.weights is not None and self.weights.input_channels != 1:
            raise WeightsError(
                f"this network takes {self.weights.input_channels}-channel images; StereoMatcher runs gray "
                "(1-channel) networks: it converts every pair to gray (imageops.to_gray) before the cost.  Run a "
                "colour network's cost directly (mccnn_cl.costs.registry.make_cost(ctx, weights)(left, right, D) "
                "with H x W x C images) or use a gray network")
        self.params = check_settings(self.weights, hyperparameters, "the weights")
        self.auto_range = isinstance(max_disparity, str) and max_disparity == "auto"
        self.max_disparity = None if self.auto_range else check_disparity_range(max_disparity)
        self.min_disparity = check_min_disparity(min_disparity)
        if self.auto_range and self.min_disparity:
            raise InputError("min_disparity is chosen per pair with max_disparity='auto'; give one or the other")
        self.cost_name = cost
        self.progress = bool(progress)
        if volume_dtype not in ("float32", "float16"):
            raise InputError(f"volume_dtype must be 'float32' or 'float16', not {volume_dtype!r}")
        self.vdtype = np.dtype(volume_dtype)
        self.half = volume_dtype == "float16"
        self.ctx = device if isinstance(device, ClContext) else ClContext(device)
        for name, value in (("memory_limit", memory_limit), ("tile_overlap", tile_overlap)):
            if value is not None and (isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer))):
                raise InputError(f"{name} must be an integer, not {value!r}")
        if memory_limit is not None and memory_limit < 1:
            raise InputError(f"memory_limit must be a positive number of bytes, not {memory_limit}")
        if tile_overlap is None or tile_overlap < 0:
            raise InputError(f"tile_overlap must be >= 0, not {tile_overlap}")
        self.memory_limit = int(memory_limit) if memory_limit is not None else int(0.75 * self.ctx.global_mem)
        self.tile_overlap = int(tile_overlap)

        # the cost stage (mccnn_cl.costs.registry): chosen from the architecture here, once
        live0 = self.ctx.memory.live
        self.cost = make_cost(self.ctx, self.weights if cost == "cnn" else "census", half=self.half)
        self.margin = self.cost.margin

        from .stages.cbca import CBCA
        from .stages.sgm_select import make_sgm

        ctx = self.ctx
        self.cross = CrossArms(ctx)
        self.cbca = CBCA(ctx, half=self.half)
        self.sgm = make_sgm(ctx, half=self.half)  # SGM or SGMWorkGroup, by the device's profile
        self.wta = WinnerTakeAll(ctx, half=self.half)
        self.right_ref = RightReference(ctx, half=self.half)
        self.lr_check = LeftRightCheck(ctx)
        self.interpolate = Interpolate(ctx)
        self.subpixel = Subpixel(ctx, half=self.half)
        self.confidence = Confidence(ctx, half=self.half)
        self.enlarge = Enlarge(ctx)
        # median_size -> MedianFilter, compiled per size: the constructor's now, others on first use (median)
        self._medians = {self.params.median_size: MedianFilter(ctx, self.params.median_size)}
        self.bilateral = BilateralFilter(ctx)
        self.range_mask = RangeMask(ctx, half=self.half)
        self._coarse = None  # the automatic range's census matcher, made on first use
        self._last_call = None  # what the kept scratch was sized for (see _compute)
        #: device bytes the constructor made (the network's weights): held for the matcher's
        #: life, they count against memory_limit (memory_plan)
        self.fixed_bytes = max(0, self.ctx.memory.live - live0)
        # cost volumes are reused between stages and calls (see release_buffers)
        self._pool = BufferPool(ctx)
        # one compute at a time: the kept volumes, the cost's scratch and the
        # queue are shared by every call (see compute, "Threads")
        self._lock = threading.RLock()

    @property
    def median(self) -> MedianFilter:
        """The median filter of ``params.median_size`` (built on first use of a size, then kept)."""
        size = int(self.params.median_size)
        stage = self._medians.get(size)
        if stage is None:
            stage = self._medians[size] = MedianFilter(self.ctx, size)
        return stage

    def _check_params(self) -> None:
        """``params`` as the constructor checks them (:class:`Hyperparameters`: names,
        choices and ranges): a field changed after construction is checked at
        every call."""
        p = self.params
        if not isinstance(p, Hyperparameters):
            raise InputError(f"StereoMatcher.params must be a Hyperparameters, not {type(p).__name__}")
        dataclasses.replace(p)  # __post_init__ runs the constructor's checks (InputError)

    @property
    def cost_floor(self) -> float:
        """The matching cost's lower bound (``cost.floor``), which the confidence measures from."""
        return self.cost.floor

    def release_buffers(self) -> None:
        """Free every device buffer kept from the last :meth:`compute`: the
        volumes (up to two), the cost's scratch (the networks' conv maps, fst's
        planar features, the "gemm" head's activations), CBCA's scratch and
        SGM's path state, the bilateral filter's tap tables, and those of the
        automatic range's census matcher.  What stays is what the constructor
        made (the network's weights, ``fixed_bytes``).

        They are kept so that the next call of the same size reuses them: on
        CPU devices a fresh buffer's first write costs several times a pass
        over it (first-touch page mapping; ~0.6 s per call on the KITTI pair
        on PoCL).  A call of another size (or range, ``memory_limit`` or
        ``params``) frees what the previous call kept before it runs, so
        that it holds what a call of its own size needs, as on a fresh matcher;
        a tiled network call frees the kept volumes before the network's bands
        and the cost's scratch after them (each phase has the limit to itself)."""
        with self._lock:
            self._pool.clear()
            self._release_scratch()
            self.bilateral.release_buffers()  # the Gaussian tap tables (made again by the next call)
            if self._coarse is not None:  # the automatic range's census matcher
                self._coarse.release_buffers()

    def _release_scratch(self) -> None:
        """Free the stages' kept scratch: the cost's, CBCA's and SGM's."""
        self.cost.release_buffers()
        self.cbca.release_buffers()
        self.sgm.release_buffers()  # SGM's path state (both SGM stages have the method)
        self._last_call = None

    # -- input checks ------------------------------------------------------
    def _inputs(self, left, right, disparity_range=None, bit_depth=None):
        """Gray images, M, D and the automatic range's report (None unless auto)."""
        I_L, I_R = to_gray(left, "left", bit_depth), to_gray(right, "right", bit_depth)
        auto = None
        given = None
        if disparity_range is None and self.auto_range:
            check_pair(I_L, I_R, 1, 2 * self.margin + 1)
            auto = self.choose_range(I_L, I_R)
            disparity_range = auto["range"]
            given = "the automatic range {}..{}"
        if disparity_range is None:
            M, D = self.min_disparity, self.max_disparity
            given = f"max_disparity={D}" + (f", min_disparity={M}" if M else "")
        else:
            M, D = levels_of(disparity_range)
            given = (given or "disparity_range=({}, {})").format(M, M + D - 1)
        check_pair(I_L, I_R, D, 2 * self.margin + 1, min_disparity=M, range_name=given)
        return I_L, I_R, M, D, auto

    def choose_range(self, left, right) -> dict:
        """The automatic disparity range of a pair (``max_disparity="auto"``):
        ``{"range": (min, max), ...}`` (:func:`mccnn_cl.disprange.choose_range`).

        Memory: the coarse passes and the full-size match are phases of their
        own, each within ``memory_limit`` beside the matcher's weights.  What
        this matcher kept from its last call (volumes, scratch) stays through
        a pass when the pass's planned peak fits ``memory_limit`` beside every
        buffer the context holds (:meth:`_room_for_pass`), so that the next
        full-size call of the same size reuses it; else it is freed before the
        pass.  What the passes kept is freed after them."""
        I_L, I_R = to_gray(left, "left"), to_gray(right, "right")
        check_pair(I_L, I_R, 1, 2 * self.margin + 1)
        with self._lock:
            try:
                return choose_range(self, I_L, I_R)
            finally:
                if self._coarse is not None:
                    self._coarse.release_buffers()

    def _room_for_pass(self, coarse, shape, window) -> None:
        """Before a coarse pass of ``coarse`` (:meth:`_coarse_matcher`) on images
        of ``shape`` over ``window`` ((lo, hi), coarse px): free what this
        matcher kept unless the pass's planned peak fits ``memory_limit``
        beside every buffer the context holds now (this matcher's weights and
        kept buffers, the coarse matcher's weights, and anything else made on
        the context: counting those too only frees more often).  The coarse
        matcher's own buffers from an earlier pass are freed first (a pass of
        another size would free them anyway).  When the pass does not fit at
        all, everything is freed and the pass's own error follows."""
        coarse.release_buffers()
        lo, hi = window
        try:
            need = coarse.memory_plan(shape, hi - lo + 1, lo).peak_bytes
        except InputError:
            need = None
        if need is None or self.ctx.memory.live + need > self.memory_limit:
            self.release_buffers()

    def _coarse_matcher(self):
        """The census matcher of the coarse passes: its calls may use ``memory_limit``
        less this matcher's weights (held beside them); its own constructor's
        buffers count in this matcher's plans (:meth:`memory_plan`)."""
        limit = max(1, self.memory_limit - self.fixed_bytes)
        if self._coarse is None:
            self._coarse = StereoMatcher(cost="census", max_disparity=2, device=self.ctx, memory_limit=limit)
        self._coarse.memory_limit = limit  # memory_limit may have changed since
        return self._coarse

    # -- the method ----------------------------------------------------------
    def compute(self, left, right, return_intermediates: bool = False, timings: bool = False,
                confidence: bool = False, disparity_range=None, bit_depth: int | None = None):
        """Disparity map (float32, the left image's size, pixels) of a rectified pair.

        ``return_intermediates``: return a :class:`StereoResult` with every
        intermediate volume and map plus per-stage times.  ``timings``: return a
        :class:`StereoResult` with per-stage times only (no copies).
        ``confidence``: return a :class:`StereoResult` whose ``confidence``
        and ``labels`` are set (computed on the final volume C; also tiled).
        ``disparity_range``: ``(min, max)`` (inclusive) for this call instead
        of the matcher's range (e.g. one from :meth:`choose_range`).
        ``bit_depth``: significant bits of integer images (e.g. 12 for 12-bit
        data in uint16; :func:`mccnn_cl.imageops.to_gray`).

        Threads: one matcher serialises its calls (a lock held for the whole
        call): calls from several threads return the results each would get
        alone, one after the other.  For parallel work give each thread its
        own matcher (the device's queue is per matcher's context).
        """
        with self._lock:
            return self._compute(left, right, return_intermediates, timings, confidence, disparity_range,
                                 bit_depth)

    def _compute(self, left, right, return_intermediates, timings, confidence, disparity_range, bit_depth):
        self._check_params()
        I_L, I_R, M, D, auto = self._inputs(left, right, disparity_range, bit_depth)
        rec = _Recorder(self.ctx, keep=return_intermediates, timed=return_intermediates or timings)
        rec.wanted = {"confidence", "labels"} if confidence else {"labels"}  # labels: check_swapped
        rec.range = (M, D)
        own = (M, D) == (self.min_disparity, self.max_disparity)  # the matcher's own range
        plan = self.memory_plan(I_L.shape) if own else self.memory_plan(I_L.shape, D, M)
        # the stages' scratch kept by a call of another size, range, limit or params is freed: this
        # call holds what its own plan counts (as a fresh matcher would), not the largest call's
        call = (I_L.shape, M, D, self.memory_limit, dataclasses.astuple(self.params))
        if call != self._last_call:
            self._release_scratch()
        self._last_call = call
        if plan.tiled and not self.cost.local:
            # the network's bands run before any tile's volume exists: the plan gives them the
            # whole limit beside the image-sized buffers, so no volume is kept through them
            self._pool.clear()
        else:
            self._pool.trim(plan.largest_volume)  # kept volumes of another size are freed
        self.ctx.memory.reset_peak()
        # buffers alive before the call (weights, other matchers' ...), less the
        # kept volumes this call reuses (they count in its peak)
        base = self.ctx.memory.live - self._pool.free_bytes
        out = self._run(I_L, I_R, rec, plan)
        labels = rec.arrays["labels"] if (confidence or return_intermediates) else rec.arrays.pop("labels")
        check_swapped(labels, out, M)
        if not (return_intermediates or timings or confidence):
            return out
        res = StereoResult(out, rec.arrays, rec.times, self.margin, rec.plan, self.ctx.memory.peak - base,
                           disparity_range=(M, M + D - 1), auto=auto)
        if confidence:  # cropped maps -> image size, border as Enlarge (refine_enlarge: clamped indices)
            pick = rec.arrays.get if return_intermediates else rec.arrays.pop
            res.confidence, res.labels = (np.pad(pick(k), self.margin, mode="edge") for k in ("confidence", "labels"))
        return res

    def _run(self, I_L, I_R, rec, plan):
        ctx, m = self.ctx, self.margin
        M, D = rec.range
        Hi, Wi = I_L.shape
        H, W = Hi - 2 * m, Wi - 2 * m
        rec.plan = plan
        d_I_L = ctx.to_device(I_L)                    # I^L, image size (bilateral)
        S_L, S_R = self._threshold_images(I_L, I_R)
        frame = None
        if M == 0:
            J_L = S_L[m:m + H, m:m + W]               # I^L, I^R on the cost volume's domain
            J_R = S_R[m:m + H, m:m + W]
        else:  # the working frame of a range not starting at 0 (mccnn_cl.disprange)
            frame = RangeFrame(M, D, (Hi, Wi), m)
            J_L, J_R = frame.thresholds(S_L, S_R)
            rec.stats = frame.stats(I_L, I_R) if self.weights is not None else None
            I_L, I_R = frame.images(I_L, I_R)
            W = frame.Ww
        rec.frame = frame
        rec.start()
        if not plan.tiled:
            volume = self._take_volume(D, H, W)
            # SGM's output volume, first written after the cost volume is complete: lent to the
            # cost meanwhile, which carves its scratch (the network's maps) from it
            lent = self._take_volume(D, H, W)
            C_CNN = self._matching_cost(I_L, I_R, D, out=volume, stats=rec.stats, scratch=lent, rows=plan.band_rows)
            self._pool.give(lent)
            C_CNN = rec("C_CNN", self._mask(C_CNN, D, H, W, rec), (D, H, W), self.vdtype)
            D_SE = self._volume_stages(C_CNN, J_L, J_R, rec)
        else:
            D_SE = ctx.to_device(self._tiled_volume_stages(I_L, I_R, J_L, J_R, plan, rec))
        if frame is not None:  # back to the image's frame and disparities
            D_SE = ctx.to_device(frame.disparity(ctx.from_device(D_SE, (H, W))))
            frame.arrays(rec.arrays)
        return self._map_stages(D_SE, d_I_L, Hi, Wi, rec)

    def _mask(self, d_cost, D, H, W, rec):
        """The padding's cells of a working-frame volume (M < 0) set to the cost ceiling."""
        f = rec.frame
        if f is not None and f.masked:
            self.range_mask(d_cost, D, H, W, f.p, f.W)
        return d_cost

    def _threshold_images(self, I_L, I_R):
        """The images the cross arms and SGM compare with cbca_tau / sgm_tau_so:
        as given (gray in [0, 1]) or each standardised over the whole image
        (``intensity_scale``; before any tiling, so tiles share one scale)."""
        if self.params.intensity_scale == "standardised":
            return normalise(I_L), normalise(I_R)
        return I_L, I_R

    def _tiled_volume_stages(self, I_L, I_R, J_L, J_R, plan, rec):
        """D_SE (host, H x W) of an image too large for one device volume: the
        volume stages run on row tiles with ``plan.overlap`` rows of overlap,
        each tile's core rows kept.  The network's volume is computed once into
        host memory and each tile's rows streamed to the device; census is
        computed per tile (it is local)."""
        ctx, m, D = self.ctx, self.margin, rec.range[1]
        H, W = J_L.shape
        host = None
        if not self.cost.local:
            host = rec("C_CNN", self._matching_cost(I_L, I_R, D, to_host=plan.tile_budget, stats=rec.stats,
                                                    rows=plan.band_rows))
            # the plan counts the cost's scratch (feature maps) in the band phase only: the tiles
            # hold volumes instead
            self.cost.release_buffers()
        D_SE = np.empty((H, W), np.float32)
        for i, (c0, c1, e0, e1) in enumerate(plan.tiles):
            log.info("tile %d/%d: volume rows %d..%d (core %d..%d)", i + 1, len(plan.tiles), e0, e1, c0, c1)
            rec.tile(c0 - e0, c1 - e0, c0, (H, W))
            if host is None:
                d_cost = rec("C_CNN", self._mask(self.cost(I_L[e0:e1 + 2 * m], I_R[e0:e1 + 2 * m], D, row0=e0,
                                                           out=self._take_volume(D, e1 - e0, W)), D, e1 - e0, W, rec))
            else:
                d_cost = self._take_volume(D, e1 - e0, W)
                ctx.cl.enqueue_copy(ctx.queue, d_cost, np.ascontiguousarray(host[:, e0:e1]))
                rec("C_CNN_upload", self._mask(d_cost, D, e1 - e0, W, rec))
            d_se = self._volume_stages(d_cost, J_L[e0:e1], J_R[e0:e1], rec)  # gives d_cost back
            del d_cost
            D_SE[c0:c1] = ctx.from_device(d_se, (e1 - e0, W))[c0 - e0:c1 - e0]
        rec.tile(None)
        return D_SE

    def _take_volume(self, D, H, W):
        """A D x H x W volume buffer (a kept one when one is free)."""
        return self._pool.take(D * H * W * self.vdtype.itemsize, "cost volume")

    def _volume_stages(self, C_CNN, J_L, J_R, rec):
        """C_CNN (device, D x h x W) through CBCA, SGM, CBCA, WTA, the left-right
        check, interpolation and subpixel enhancement; returns D_SE (device).
        ``J_L``, ``J_R``: the images on the volume's domain (host, h x W).
        C_CNN's buffer and every volume made here go back to the pool."""
        p, ctx, D = self.params, self.ctx, rec.range[1]
        H, W = J_L.shape
        vol, crop = (D, H, W), (H, W)
        d_J_L = ctx.to_device(np.ascontiguousarray(J_L))
        d_J_R = ctx.to_device(np.ascontiguousarray(J_R))
        # CBCA aggregates in place (out=its input): a recorded volume is copied
        # to the host before the next stage overwrites it.
        arm = max_arm(p.cbca_eta, p.cross_include_neighbor)
        arms_L, arms_R = self._arms(d_J_L, d_J_R, H, W, rec, "cross")
        C_CBCA = rec("C_CBCA", self._cbca(C_CNN, arms_L, arms_R, D, H, W, p.cbca_iterations, arm), vol, self.vdtype)
        if p.right_reference == "aggregated":
            # The right reference's first CBCA is this one, shifted: its support
            # regions are the left ones moved by -d (docs/method.md, 5.).  Its
            # volume is C_CBCA mirrored: read so by SGM's paired sweeps, else
            # mirrored in place, run to D_R first and mirrored back, so that two
            # volumes are alive at once, not three.
            if self.sgm.reads_mirrored:
                D_R = rec("D_R", self._right_reference(C_CBCA, J_L, J_R, rec, mirrored=True), crop, np.int32)
            else:
                C_R = rec("right_volume", self.right_ref.volume(C_CBCA, D, H, W))
                D_R = rec("D_R", self._right_reference(C_R, J_L, J_R, rec), crop, np.int32)
                rec("right_volume", self.right_ref.volume(C_R, D, H, W))  # C_CBCA again
        C_SGM = rec("C_SGM", self.sgm(C_CBCA, d_J_L, d_J_R, D, H, W, p.sgm_pi1, p.sgm_pi2, p.sgm_tau_so,
                                      p.sgm_q1, p.sgm_q2, p.sgm_v, p.sgm_variant, p.sgm_p2_times_pi1,
                                      p.sgm_outside_large, out=self._take_volume(D, H, W),
                                      cost_bound=self._sgm_bound()), vol, self.vdtype)
        self._pool.give(C_CBCA)  # C_CNN's buffer, aggregated in place; free for the right SGM
        C = rec("C", self._cbca(C_SGM, arms_L, arms_R, D, H, W, p.cbca_iterations_after, arm), vol, self.vdtype)
        D_L = rec("D_L", self.wta.left(C, D, H, W), crop, np.int32)
        if p.right_reference == "derived":
            D_R = rec("D_R", self.wta.right(C, D, H, W), crop, np.int32)
        # a working frame with padding (M < 0): the right image's real columns 0 .. f.W-1, the left's f.p ..
        # W-1; the check, interpolation and subpixel see only real pixels (docs/method.md, "Disparity ranges")
        f = rec.frame
        Wr, lo = (f.W, f.p) if f is not None and f.masked else (W, 0)
        labels = rec("labels", self.lr_check(D_L, D_R, D, H, W, p.lr_threshold, right_width=Wr), crop, np.int32)
        D_INT = rec("D_INT", self.interpolate(D_L, labels, H, W, p.interpolation, first_column=lo), crop, np.int32)
        D_SE = rec("D_SE", self.subpixel(C, D_INT, D, H, W, p.subpixel_min_denominator, p.subpixel_clamp,
                                         right_width=Wr), crop)
        if "confidence" in rec.wanted:
            rec("confidence", self.confidence(C, labels, D, H, W, self.cost.floor, right_width=Wr, first_column=lo),
                crop)
        self._pool.give(C)  # the in-order queue runs any later user after subpixel
        return D_SE

    def _sgm_bound(self):
        """``cost_bound`` for SGM: the cost's max |C| with ``sgm_int16``, else None (float SGM)."""
        return self.cost.magnitude_bound() if self.params.sgm_int16 else None

    def _arms(self, d_left, d_right, H, W, rec, name):
        """Cross arms of both images, or (None, None) when no CBCA runs
        (``cbca_iterations == cbca_iterations_after == 0``, the fst settings)."""
        p = self.params
        if p.cbca_iterations == 0 and p.cbca_iterations_after == 0:
            return None, None
        arms_L = self.cross(d_left, H, W, p.cbca_tau, p.cbca_eta, p.cross_include_neighbor)
        return arms_L, rec(name, self.cross(d_right, H, W, p.cbca_tau, p.cbca_eta, p.cross_include_neighbor))

    def _cbca(self, d_cost, arms_L, arms_R, D, H, W, iterations, arm):
        """CBCA in place, ``iterations`` times (none: the volume as it is)."""
        if iterations == 0:
            return d_cost
        return self.cbca(d_cost, arms_L, arms_R, D, H, W, iterations, arm, out=d_cost)

    def _map_stages(self, D_SE, d_I_L, Hi, Wi, rec):
        """D_SE (device, cropped domain) -> enlarged, median, bilateral: D_BF (host)."""
        p, m = self.params, self.margin
        H, W = Hi - 2 * m, Wi - 2 * m
        img = (Hi, Wi)
        D_E = rec("D_E", self.enlarge(D_SE, H, W, Hi, Wi, m), img)
        D_median = rec("D_median", self.median(D_E, Hi, Wi), img)
        guide, tau = (d_I_L, p.blur_tau / 255.0) if p.bilateral_guide == "image" else (D_median, p.blur_tau)
        D_BF = rec("D_BF", self.bilateral(D_median, guide, Hi, Wi, p.blur_sigma, tau, p.blur_radius), img)
        return self.ctx.from_device(D_BF, img)

    def _right_reference(self, C_R, J_L, J_R, rec, mirrored=False):
        """D^R with the right image as the reference (``right_reference="aggregated"``):
        the mirrored right-reference volume after its first CBCA (``C_R``, the
        shifted, mirrored C_CBCA; network not rerun) through SGM, CBCA and the
        left WTA with the mirrored right and left images as (left, right); the
        map is mirrored back.  ``mirrored``: ``C_R`` is C_CBCA itself, which
        SGM reads mirrored (``SGM(mirror=True)``).  ``C_R`` is read, not
        changed, and stays the caller's."""
        p, ctx, D = self.params, self.ctx, rec.range[1]
        H, W = J_L.shape
        d_K_L = ctx.to_device(np.ascontiguousarray(J_R[:, ::-1]))  # mirrored right image
        d_K_R = ctx.to_device(np.ascontiguousarray(J_L[:, ::-1]))  # mirrored left image
        arm = max_arm(p.cbca_eta, p.cross_include_neighbor)
        arms_L, arms_R = self._arms(d_K_L, d_K_R, H, W, rec, "cross_R")
        C_R_SGM = rec("C_R_SGM", self.sgm(C_R, d_K_L, d_K_R, D, H, W, p.sgm_pi1, p.sgm_pi2, p.sgm_tau_so,
                                          p.sgm_q1, p.sgm_q2, p.sgm_v, p.sgm_variant, p.sgm_p2_times_pi1,
                                          p.sgm_outside_large, out=self._take_volume(D, H, W), mirror=mirrored,
                                          cost_bound=self._sgm_bound()))
        C_R = rec("C_R", self._cbca(C_R_SGM, arms_L, arms_R, D, H, W, p.cbca_iterations_after, arm),
                  (D, H, W), self.vdtype)
        D_R = self.right_ref.mirror(self.wta.left(C_R, D, H, W), H, W)
        self._pool.give(C_R)
        return D_R

    def _matching_cost(self, I_L, I_R, D, to_host=None, out=None, stats=None, scratch=None, rows=None):
        """C_CNN on the device (into ``out`` when given; ``scratch`` lent to the
        cost for the call), or with ``to_host`` (bytes of device memory the
        bands may use; network only) as a host array computed band by band;
        ``rows``: the network's band rows (the plan's ``band_rows``)."""
        def run(progress=None):
            kw = {"rows": rows} if rows is not None else {}
            if stats is not None:  # a working frame's padded images: the real images' standardisation
                kw["stats"] = stats
            if to_host is not None:
                return self.cost.to_host(I_L, I_R, D, max_bytes=to_host, progress=progress, **kw)
            return self.cost(I_L, I_R, D, progress=progress, out=out, scratch=scratch, **kw)

        if not self.progress:
            return run()
        from tqdm.auto import tqdm

        with tqdm(total=D, desc=f"cost volume ({self.cost_name})", unit="disp") as bar:
            def report(done, total):
                bar.update(done - bar.n)
            out = run(report)
            self.ctx.finish()
            bar.update(D - bar.n)
        return out

    # -- memory --------------------------------------------------------------
    def memory_plan(self, shape, levels=None, min_disparity=None) -> "MemoryPlan":
        """How :meth:`compute` will use device memory for images of ``shape``
        (H_img, W_img): the whole image at once when its volumes fit
        ``memory_limit`` and the device's max allocation, else row tiles.
        ``levels``, ``min_disparity``: the range (default: the matcher's; with
        ``max_disparity="auto"`` ``levels`` must be given); a range not
        starting at 0 runs on images W_img - min_disparity wide (mccnn_cl.disprange).

        The network's bands are sized here too (``band_rows``): the cost's own
        (``BAND_BYTES``) when they fit, else the most rows whose band fits the
        limit: beside the whole image's volumes (at least ``MIN_BAND_ROWS``
        rows, else row tiles), or, tiled, beside the image-sized buffers alone
        (the kept volumes are freed before the bands, the bands' feature maps
        before the tiles)."""
        D = self.max_disparity if levels is None else int(levels)
        M = self.min_disparity if min_disparity is None else int(min_disparity)
        if D is None:
            raise InputError("memory_plan needs levels= with max_disparity='auto' (the range is chosen per pair)")
        Hi, Wi = int(shape[0]), int(shape[1]) - M
        m = self.margin
        H, W = Hi - 2 * m, Wi - 2 * m
        row = D * W * self.vdtype.itemsize                 # one volume row, bytes
        nvol = 2  # the cost volume (CBCA in place; mirrored in place for the right reference) and SGM's output
        maps = MAP_BUFFERS * Hi * Wi * 4                    # images, arms, disparity maps
        for stage in (self.cbca, self.sgm):  # CBCA's rings, SGM's vertical path state
            maps += stage.scratch_bytes(D, W, self.params)
        cost = self.cost
        banded = not cost.local  # the networks: in bands of volume rows (sized here)
        most = cost.band_rows(H, W) if banded else None
        # what the calls may use: the limit less the constructor's buffers (the weights) and those of
        # the automatic range's census matcher once made (its kept ones are freed before a call: choose_range)
        limit, own, max_alloc = self.memory_limit, self.fixed_bytes, self.ctx.max_alloc
        if self._coarse is not None:
            own += self._coarse.fixed_bytes
        budget = limit - own

        def whole(rows):  # SGM's output volume is lent to the cost, which carves scratch from it
            return (nvol * row * H + cost.scratch_bytes(H, W, rows) - cost.lent_scratch_bytes(H, W, row * H, rows)
                    + maps)

        overlap = self.tile_overlap
        if row * H <= max_alloc:
            rows = most
            if banded and whole(most) > budget:  # thinner bands, if that keeps the whole image at once
                thin = _largest(lambda r: whole(r) <= budget, most)
                rows = thin if thin >= min(most, MIN_BAND_ROWS) else most
            if whole(rows) <= budget:
                return MemoryPlan(row * H, nvol, whole(rows), limit, [(0, H, 0, H)], overlap, 0, limit, False, rows)
        # device bytes per tile row: the volumes, and census's bits (computed per
        # tile; the network runs once, before the tiles, into host memory)
        per_row = nvol * row + (cost.scratch_bytes(1, W) if cost.local else 0)
        ext = min(max_alloc // row, max(0, budget - maps) // per_row)
        n = 1  # the fewest tiles whose largest extent fits; the end tiles overlap on their inner side only
        while ext < H and n is not None:
            n += 1
            core = -(-H // n)
            if core < MIN_TILE_ROWS:
                n = None
            elif min(H, core + overlap * (1 if n == 2 else 2)) <= ext:
                break
        if n is None:
            need = per_row * min(H, 2 * overlap + MIN_TILE_ROWS) + maps + own
            raise InputError(
                f"{Wi}x{Hi} with {D} disparities does not fit: row tiles of {MIN_TILE_ROWS} rows plus "
                f"{overlap} rows of overlap on each side need {need / 2**20:.1f} MiB of device memory "
                f"(memory_limit {limit / 2**20:.1f} MiB, max allocation {max_alloc / 2**20:.0f} MiB on "
                f"{self.ctx.describe()}); reduce the disparity range or the image width, or raise memory_limit")
        core = -(-H // n)
        tiles = [(c0, min(H, c0 + core), max(0, c0 - overlap), min(H, c0 + core + overlap))
                 for c0 in range(0, H, core)]
        ext_max = max(e1 - e0 for _, _, e0, e1 in tiles)
        peak = per_row * ext_max + maps  # the tiles: no network scratch (freed after its bands)
        host, band_budget, rows = 0, 0, None
        if banded:  # the network's phase, before the tiles (no volume kept): one band volume + its scratch
            host = row * H

            def band(r):
                return r * row + cost.scratch_bytes(H, W, r) + maps

            rows = _largest(lambda r: r * row <= max_alloc and band(r) <= budget, most)
            if rows == 0:  # not even a one-row band fits beside its feature maps
                raise InputError(
                    f"{Wi}x{Hi} does not fit: the network's feature maps and buffers need "
                    f"{(band(1) + own) / 2**20:.1f} MiB of device memory for bands of one row (memory_limit "
                    f"{limit / 2**20:.1f} MiB on {self.ctx.describe()}); reduce the image size or raise memory_limit")
            band_budget = rows * row
            peak = max(peak, band(rows))
        return MemoryPlan(row * H, nvol, peak, limit, tiles, overlap, host, band_budget, True, rows)


#: Thresholds of :func:`check_swapped`, measured on real pairs of
#: ../shared/data in both orders (docs/method.md, "Swapped pairs"): with the
#: correct order the left-right check labels at most 10.3 % of the pixels
#: mismatch and at most 33 % of the map lies below 1.5 px; swapped, either
#: over 20 % mismatch (large disparities) or over 5 % mismatch with more than
#: half of the map below 1.5 px (small disparities: the minima pile up at d = 0,
#: the nearest candidate to the true negative disparity).
SWAP_MISMATCH = 0.2
SWAP_MISMATCH_NEAR = 0.04
SWAP_NEAR_ZERO = 0.5


def check_swapped(labels, disparity, low: int = 0) -> bool:
    """Warn (:class:`~mccnn_cl.errors.InputWarning`, naming the likely cause)
    when the left-right labels (1 = mismatch) and the disparity map look like a
    swapped pair: its true disparities are negative, outside the searched
    0 .. D-1, so the two references disagree on many pixels and the minima
    gather at the range's near end (``low``, the range's first disparity).
    Returns whether it warned."""
    labels, disparity = np.asarray(labels), np.asarray(disparity)
    if not labels.size or not disparity.size:
        return False
    mismatch = float(np.mean(labels == 1))
    near = float(np.mean(disparity < low + 1.5))
    if mismatch > SWAP_MISMATCH or (mismatch > SWAP_MISMATCH_NEAR and near > SWAP_NEAR_ZERO):
        import warnings

        from .errors import InputWarning
        from .imageops import user_stacklevel
        warnings.warn(f"the left-right check failed on {mismatch:.0%} of the pixels and {near:.0%} of the map is "
                      f"below {low + 1.5:g} px: are the left and right images swapped? (else: the pair is not rectified, "
                      "or the disparity range is too small)", InputWarning, stacklevel=user_stacklevel())
        return True
    return False


class _Recorder:
    """Per-stage bookkeeping of :meth:`StereoMatcher._run`: when timed, waits for
    the queue after each stage and adds the wall time since the previous stage
    to that stage's total (tiles add up); when keeping, copies the stage's
    output buffer to the host.  Inside a tile (:meth:`tile`) volumes are not
    kept and maps keep only the tile's core rows, placed in full-size arrays."""

    def __init__(self, ctx, keep: bool, timed: bool):
        self.ctx, self.keep, self.timed = ctx, keep, timed
        self.arrays, self.times = {}, {}
        self.t = 0.0
        self.plan = None
        self._tile = None
        self.wanted = set()  # names kept even when not keeping (compute's confidence=True)
        self.range = (0, 0)   # (M, D) of the call
        self.frame = None     # its disprange.RangeFrame when M != 0
        self.stats = None     # the real images' standardisation (networks, M != 0)

    def start(self):
        if self.timed:
            self.ctx.finish()
            self.t = time.perf_counter()

    def tile(self, r0, r1=None, y0=None, full=None):
        """Inside a tile: rows r0..r1 of its maps are rows y0.. of a ``full``-shaped map.
        ``tile(None)``: outside tiles."""
        self._tile = None if r0 is None else (r0, r1, y0, full)

    def __call__(self, name, buf, shape=None, dtype=np.float32):
        self.ctx.pace()  # about two stages queued ahead at most: Ctrl-C answers within a stage's time
        if self.timed:
            self.ctx.finish()
            now = time.perf_counter()
            self.times[name] = self.times.get(name, 0.0) + now - self.t
        if (self.keep or name in self.wanted) and shape is not None:
            if self._tile is None:
                self.arrays[name] = self.ctx.from_device(buf, shape, dtype)
            elif len(shape) == 2:
                r0, r1, y0, full = self._tile
                if name not in self.arrays:
                    self.arrays[name] = np.empty(full, dtype)
                self.arrays[name][y0:y0 + r1 - r0] = self.ctx.from_device(buf, shape, dtype)[r0:r1]
        if self.timed:
            self.t = time.perf_counter()  # copies do not count
        return buf
