"""Stereo pairs on a Dask cluster: :func:`match_pairs` and ``mccnn-cl match --workers N``.

Each worker process keeps one OpenCL context and one :class:`StereoMatcher`
per configuration (:func:`matcher_config`: cost, weights, device, memory
limit, volume storage, hyperparameters) and disparity range, built by its
first task and reused by every later one (volumes and built kernels kept
warm).  A worker is pinned to one device: the ``device`` of the
configuration when given (or ``$PYOPENCL_CTX``), else, on a ``LocalCluster``
whose workers are named 0, 1, ..., worker i takes device i (modulo their
number) of the preferred kind (GPUs first), so a machine with k GPUs runs k
workers on k devices (:func:`worker_device`; ``mccnn-cl devices --workers N``
shows the choice).

A pair is one task: the worker reads the images, matches them and returns
the maps; the client writes the outputs (:func:`mccnn_cl.batch.write_pair`,
the same writer as the one-process batch), so a worker killed mid-task
leaves nothing behind and its task is run again elsewhere by the scheduler.

A pair whose memory plan has row tiles (:meth:`StereoMatcher.memory_plan`)
can be split over the workers (``split_tiles``; by default when the batch has
fewer pairs than workers): the plan is made on every worker first (a tile
that does not fit a worker's device, or the worker's memory limit, is an
error before any tile runs), the plan with the most tiles is used (it fits
every worker), each tile's volume stages run as a task -- the worker reads
the pair, computes the tile's cost volume from the tile's rows (the network
from the image standardised as a whole, so the rows equal the whole image's
volume rows) and returns the tile's core rows of D_SE -- and a last task
assembles them and runs the image-sized stages.  The map equals the one
process's tiled run bit for bit (``tests/test_distributed.py``).
"""

from __future__ import annotations

import json
import logging
import os
import threading

import numpy as np

from .batch import (Job, PairResult, Progress, Summary, _probe_size, batch_range, compute_pair, describe_failure,
                    done_line, storage_stop, write_pair)
from .errors import InputError

log = logging.getLogger(__name__)

# -- worker side -----------------------------------------------------------------

_LOCK = threading.Lock()          # one matcher call at a time per worker process
_CONTEXTS: dict = {}              # device spec -> ClContext
_MATCHERS: dict = {}              # (configuration, max_disp) -> StereoMatcher


def matcher_config(cost="cnn", weights=None, device=None, memory_limit=None, volume_dtype="float32",
                   min_disparity=0, **hyperparameters) -> dict:
    """A picklable description of the matcher every worker builds (and keeps):
    ``weights`` a shipped name or a path (made absolute), ``memory_limit``
    bytes.  Keys of the per-worker matcher cache."""
    return {"cost": cost, "weights": _absolute(weights), "device": device,
            "memory_limit": None if memory_limit is None else int(memory_limit),
            "volume_dtype": volume_dtype, "min_disparity": int(min_disparity), "hyper": dict(hyperparameters)}


def _absolute(weights):
    """``weights`` made absolute when it names a file here (a path, not a shipped model's name): a
    worker takes a relative path in its own working folder (:func:`for_workers`)."""
    if isinstance(weights, str) and os.path.exists(weights):
        return os.path.abspath(weights)
    return weights


def _key(config, max_disp):
    return json.dumps(config, sort_keys=True, default=str), (max_disp if max_disp == "auto" else int(max_disp))


def worker_index():
    """This worker's number on a LocalCluster (its name), else None."""
    try:
        from distributed import get_worker
        name = get_worker().name
    except (ImportError, ValueError):
        return None
    return name if isinstance(name, int) else None


def worker_device(spec=None, index=None):
    """``(DeviceInfo, reason)``: the device worker ``index`` uses (module docstring)."""
    from .opencl.context import list_devices, select_device
    devices = list_devices()
    if spec is not None or os.environ.get("PYOPENCL_CTX") or index is None:
        handle, reason = select_device(spec)
        return next(d for d in devices if d.handle == handle), reason
    top = devices[0]
    same = [d for d in devices if d.type == top.type and d.platform == top.platform]
    pick = same[index % len(same)]
    return pick, (f"worker {index} of a local cluster: {top.type} device {index % len(same)} of "
                  f"{len(same)} on {top.platform}")


def _matcher(config, max_disp):
    """This worker's kept matcher for ``config`` and ``max_disp`` (D, or "auto":
    each pair its own range; built on first use)."""
    key = _key(config, max_disp)
    matcher = _MATCHERS.get(key)
    if matcher is None:
        from .opencl.context import ClContext
        from .pipeline import StereoMatcher
        dev_key = json.dumps([config["device"], worker_index()])
        ctx = _CONTEXTS.get(dev_key)
        if ctx is None:
            info, reason = worker_device(config["device"], worker_index())
            log.info("worker %s: %s (%s)", worker_index(), info, reason)
            ctx = _CONTEXTS[dev_key] = ClContext(info.handle)
        kwargs = dict(max_disparity=key[1], device=ctx, cost=config["cost"],
                      volume_dtype=config["volume_dtype"], **config["hyper"])
        if config.get("min_disparity"):
            kwargs["min_disparity"] = config["min_disparity"]
        if config["cost"] == "cnn":
            kwargs["weights"] = config["weights"]
        if config["memory_limit"] is not None:
            kwargs["memory_limit"] = config["memory_limit"]
        matcher = _MATCHERS[key] = StereoMatcher(**kwargs)
    return matcher


def _where(matcher):
    return f"worker {worker_index()} ({matcher.ctx.describe()})"


def warm(config, max_disp):
    """Build this worker's matcher (run on every worker before the first pair)."""
    with _LOCK:
        return _where(_matcher(config, max_disp))


def pair_task(config, job, max_disp, want_confidence) -> PairResult:
    """Task: match one whole pair on this worker."""
    with _LOCK:
        res = compute_pair(job, lambda d: _matcher(config, d), max_disp, want_confidence)
        res.where = _where(_matcher(config, max_disp))
    return res


def plan_task(config, shape, max_disp, dask_worker=None) -> dict:
    """Run on every worker: its memory plan for images of ``shape`` (raises
    InputError when a tile cannot fit its device or its memory limit)."""
    from .pipeline import MAP_BUFFERS
    m = _MATCHERS.get(_key(config, max_disp))
    if m is None:  # normally built by warm(); client.run calls this beside a running task
        with _LOCK:
            m = _matcher(config, max_disp)
    plan = m.memory_plan(shape)  # device facts only: no queue work, no lock needed
    Hi, Wi = int(shape[0]), int(shape[1])
    H, W = Hi - 2 * m.margin, Wi - 2 * m.margin
    # host bytes of one tile task: images (gray, thresholds, standardised) and, for
    # a network, the tile's volume; on a CPU device its buffers are host memory too
    ext = max(e1 - e0 for _, _, e0, e1 in plan.tiles)
    host = 8 * Hi * Wi * 4 + (0 if m.cost.local else max(m.max_disparity * ext * W * m.vdtype.itemsize, 0))
    if m.ctx.device.type & m.ctx.cl.device_type.CPU:
        host += max(plan.peak_bytes, MAP_BUFFERS * Hi * Wi * 4)
    limit = None
    if dask_worker is not None:
        limit = getattr(getattr(dask_worker, "memory_manager", None), "memory_limit", None)
    if limit and host > 0.8 * limit:
        raise InputError(f"{Wi}x{Hi} with {m.max_disparity} disparities: a tile needs about "
                         f"{host / 2**20:.0f} MiB of host memory on {_where(m)}, more than 80% of the "
                         f"worker's memory limit ({limit / 2**20:.0f} MiB); lower --memory-limit (smaller "
                         "tiles) or give the workers more memory")
    return {"tiles": [tuple(int(v) for v in t) for t in plan.tiles], "tiled": plan.tiled,
            "tile_budget": int(plan.tile_budget), "peak": int(plan.peak_bytes), "budget": int(plan.budget),
            "describe": plan.describe(), "where": _where(m), "margin": m.margin, "H": H, "W": W}


def _prepared(m, job):
    """The pair as :meth:`StereoMatcher.compute` sees it: (I_L, I_R, J_L, J_R)."""
    from .cli.common import _gray
    from .io import read_image
    I_L, I_R = m._inputs(_gray(read_image(job.left)), _gray(read_image(job.right)))[:2]
    S_L, S_R = m._threshold_images(I_L, I_R)
    mg = m.margin
    H, W = I_L.shape[0] - 2 * mg, I_L.shape[1] - 2 * mg
    return I_L, I_R, S_L[mg:mg + H, mg:mg + W], S_R[mg:mg + H, mg:mg + W]


def tile_task(config, job, max_disp, tile, tile_budget, want_confidence):
    """Task: one row tile's volume stages (as :meth:`StereoMatcher._tiled_volume_stages`
    runs them); returns the core rows of (D_SE, confidence, labels)."""
    from .pipeline import _Recorder
    from .imageops import image_stats
    c0, c1, e0, e1 = tile
    with _LOCK:
        m = _matcher(config, max_disp)
        I_L, I_R, J_L, J_R = _prepared(m, job)
        ctx, mg, D = m.ctx, m.margin, m.max_disparity
        W = J_L.shape[1]
        rec = _Recorder(ctx, keep=False, timed=False)
        rec.range = (0, D)  # split tiles run ranges starting at 0 (match_pairs)
        rec.wanted = {"confidence", "labels"} if want_confidence else set()
        rec.tile(c0 - e0, c1 - e0, 0, (c1 - c0, W))
        m._pool.trim(m.memory_plan(I_L.shape).largest_volume)  # as compute() does
        if m.cost.local:
            d_cost = m.cost(I_L[e0:e1 + 2 * mg], I_R[e0:e1 + 2 * mg], D, out=m._take_volume(D, e1 - e0, W), row0=e0)
        else:  # the network on the tile's rows of the whole image's standardisation
            stats = (image_stats(I_L), image_stats(I_R))
            # as StereoMatcher._tiled_volume_stages: no kept volume during the network's bands (the plan
            # does not count one there), and no feature maps during the volume stages
            m._pool.clear()
            host = m.cost.to_host(I_L[e0:e1 + 2 * mg], I_R[e0:e1 + 2 * mg], D, max_bytes=tile_budget,
                                  stats=stats, row0=e0)
            m.cost.release_buffers()
            d_cost = m._take_volume(D, e1 - e0, W)
            ctx.cl.enqueue_copy(ctx.queue, d_cost, np.ascontiguousarray(host))
            del host
        d_se = m._volume_stages(d_cost, J_L[e0:e1], J_R[e0:e1], rec)
        del d_cost
        core = ctx.from_device(d_se, (e1 - e0, W))[c0 - e0:c1 - e0].copy()
        return core, rec.arrays.get("confidence"), rec.arrays.get("labels")


def finish_task(config, job, max_disp, tiles, parts, want_confidence) -> PairResult:
    """Task: the tiles' D_SE rows assembled, then the image-sized stages (as
    :meth:`StereoMatcher._run` after its tiles)."""
    import time

    from .pipeline import _Recorder
    t0 = time.perf_counter()
    with _LOCK:
        m = _matcher(config, max_disp)
        I_L, _, J_L, _ = _prepared(m, job)
        Hi, Wi = I_L.shape
        H, W = J_L.shape
        D_SE = np.empty((H, W), np.float32)
        conf = np.empty((H, W), np.float32) if want_confidence else None
        labels = np.empty((H, W), np.int32) if want_confidence else None
        for (c0, c1, _, _), (core, c, lab) in zip(tiles, parts):
            D_SE[c0:c1] = core
            if want_confidence:
                conf[c0:c1], labels[c0:c1] = c, lab
        rec = _Recorder(m.ctx, keep=False, timed=False)
        rec.range = (0, m.max_disparity)
        disp = m._map_stages(m.ctx.to_device(D_SE), m.ctx.to_device(I_L), Hi, Wi, rec)
        res = PairResult(disp, int(max_disp), time.perf_counter() - t0,
                         where=f"{len(tiles)} row tiles on the workers, assembled on {_where(m)}")
        if want_confidence:
            res.confidence, res.labels = (np.pad(a, m.margin, mode="edge") for a in (conf, labels))
        return res


# -- client side -----------------------------------------------------------------

def local_cluster(n_workers: int, **kwargs):
    """A LocalCluster of ``n_workers`` processes with one thread each (no dashboard)."""
    from distributed import LocalCluster
    opts = dict(n_workers=int(n_workers), threads_per_worker=1, processes=True, dashboard_address=None,
                silence_logs=logging.ERROR)
    opts.update(kwargs)
    import warnings
    with warnings.catch_warnings():  # the scheduler's HTTP routes move off a busy port 8787: nothing to act on
        warnings.filterwarnings("ignore", message="Port 8787 is already in use")
        return LocalCluster(**opts)


def n_workers(client) -> int:
    return len(client.scheduler_info()["workers"])


def _from_0(min_disparity, max_disp) -> bool:
    """Whether the range is searched from disparity 0 (no minimum, not automatic): the frame of
    row tiles over several workers."""
    return not min_disparity and max_disp != "auto"


def check_split_tiles(split_tiles, min_disparity, max_disp) -> None:
    """Split tiles (``--split-tiles``) need a range from 0 (:func:`_from_0`): InputError with a
    minimum disparity or an automatic range (``max_disp`` "auto").  ``mccnn-cl match`` asks before
    anything else of the cluster path (:func:`run`), so that no cluster starts (nor output folder
    is made) for it."""
    if split_tiles and not _from_0(min_disparity, max_disp):
        raise InputError("row tiles over several workers search disparities from 0: "
                         "--split-tiles cannot be combined with --min-disp or --disp-range auto")


def for_workers(job) -> Job:
    """``job`` as its tasks are sent: every path (images, disparity map, side files) made absolute
    here, in the client's working folder.  A worker resolves a relative path in its own working
    folder (another one on an existing cluster), where ``left.png`` names no file or another one."""
    return Job(job.name, os.path.abspath(job.left), os.path.abspath(job.right), os.path.abspath(job.out),
               [os.path.abspath(p) for p in job.sides])


def _as_given(exc, spellings):
    """``exc`` with every path of ``spellings`` (``{path sent: path as the user gave it}``) in its
    message written as the user gave it: a worker (or the client reading a sent path) names the
    absolute path it was sent (:func:`for_workers`), which the user never typed.  Changed in
    place, only when the message is the exception's one text argument (``InputError("file not
    found: ...")``); any other exception is left as it is.  Returns ``exc``."""
    text = str(exc)
    new = text
    for sent in sorted(spellings, key=len, reverse=True):  # longest first: a path may start another
        new = new.replace(sent, spellings[sent])
    if new != text and len(exc.args) == 1 and exc.args[0] == text:
        exc.args = (new,)
        if str(exc) != new:  # a __str__ of its own: leave it as it was
            exc.args = (text,)
    return exc


def _spellings(pairs) -> dict:
    """``{path sent: the user's spelling}`` of ``(sent, given)`` path pairs, where they differ."""
    return {s: g for s, g in pairs if isinstance(s, str) and isinstance(g, str) and s and s != g}


def _paths(sent, given) -> list:
    """``(path sent, path given)`` of a job's images and outputs (:func:`for_workers`)."""
    return [(sent.left, given.left), (sent.right, given.right), (sent.out, given.out),
            *zip(sent.sides, given.sides)]


def match_pairs(client, jobs, config, max_disp, want_confidence=False, split_tiles=None, progress=False):
    """Match ``jobs`` (:class:`mccnn_cl.batch.Job`) on ``client``'s workers;
    yields ``(job, PairResult)`` or ``(job, exception)`` as pairs complete.

    Relative paths of the jobs (and of ``config``'s weights file,
    :func:`matcher_config`) mean files of this process's working folder: the
    workers are sent them absolute (:func:`for_workers`); the jobs yielded are
    those given, and the failures' messages name their paths as given
    (:func:`_as_given`).  ``split_tiles``: run the row tiles of a pair whose plan is
    tiled as tasks of their own (module docstring); None: when there are fewer
    pairs than workers.  Closing the generator early (or an interrupt) cancels
    the pairs not done."""
    from distributed import as_completed

    from .io import read_image
    check_split_tiles(split_tiles, config.get("min_disparity"), max_disp)
    workers = max(1, n_workers(client))
    if not _from_0(config.get("min_disparity"), max_disp):
        split_tiles = False  # a range not starting at 0 runs whole pairs (StereoMatcher.compute's frame)
    if split_tiles is None:
        split_tiles = len(jobs) < workers
    weights = config.get("weights")
    config = {**config, "weights": _absolute(weights)}
    named = [(config["weights"], weights)]  # the weights file as sent and as given
    try:
        client.run(warm, config, max_disp)  # every worker builds its matcher now, in parallel
    except Exception as exc:
        _as_given(exc, _spellings(named))
        raise
    owner, futures, tile_futures = {}, [], []
    failed_early = []
    for given in jobs:
        job = for_workers(given)
        if split_tiles:
            try:
                shape = read_image(job.left).shape[:2]
                plans = client.run(plan_task, config, shape, max_disp)
            except Exception as exc:  # noqa: BLE001 - this pair fails, before any of its work
                failed_early.append((given, _as_given(exc, _spellings(_paths(job, given) + named))))
                continue
            plan = max(plans.values(), key=lambda p: len(p["tiles"]))
            if plan["tiled"] and len(plan["tiles"]) > 1:
                log.info("%s: %s; %d tiles over %d workers", job.name, plan["describe"], len(plan["tiles"]), workers)
                parts = [client.submit(tile_task, config, job, max_disp, t, plan["tile_budget"], want_confidence,
                                       pure=False, key=f"tile-{job.name}-{i}-{os.urandom(4).hex()}")
                         for i, t in enumerate(plan["tiles"])]
                tile_futures += parts
                fut = client.submit(finish_task, config, job, max_disp, plan["tiles"], parts, want_confidence,
                                    pure=False)
                owner[fut.key] = given, job
                futures.append(fut)
                continue
        fut = client.submit(pair_task, config, job, max_disp, want_confidence, pure=False)
        owner[fut.key] = given, job
        futures.append(fut)
    for job, exc in failed_early:
        yield job, exc
    bars = []
    if progress:  # a bar on a terminal, else a line now and then (mccnn_cl.batch.Progress)
        bars.append(Progress(len(futures)))
        if tile_futures:
            bars.append(Progress(len(tile_futures), unit="tile", desc="tiles", position=1))
    done = set()
    try:
        for fut in as_completed(futures + tile_futures):
            if fut.key not in owner:
                if len(bars) > 1:
                    bars[1].update(1)
                continue
            job, sent = owner[fut.key]
            exc = fut.exception()
            if exc is not None:  # its message in the user's spelling of the paths
                exc = _as_given(exc, _spellings(_paths(sent, job) + named))
            outcome = exc if exc is not None else fut.result()
            done.add(fut.key)
            if bars:
                bars[0].update(1)
            yield job, outcome
            fut.release()
    finally:
        pending = [f for f in futures + tile_futures if f.key not in done and not f.done()]
        if pending:
            client.cancel(pending)
        for b in bars:
            b.close()


def _single_job(args, calib=None):
    """The one pair of ``match LEFT RIGHT -o OUT --workers N`` as a :class:`Job` (checked as the
    one-process path: an output that is an input, even with ``--force``, and a ``.png`` for a
    stated range it cannot hold are refused)."""
    from .batch import check_png_range
    from .cli.common import DISPARITY_FORMATS, _check_outputs, _confidence_outputs, _side_outputs
    if args.left is None or args.right is None or args.output is None:
        raise InputError("match needs LEFT RIGHT and -o OUT")
    if args.output_dir:
        raise InputError("--output-dir is for batches (-l/-r); use -o for one pair")
    for f in (args.left, args.right):
        if not os.path.isfile(f):
            raise InputError(f"file not found: {f}")
    out = args.output
    if os.path.splitext(out)[1].lower() not in DISPARITY_FORMATS:
        raise InputError(f"{out}: output must end in {', '.join(DISPARITY_FORMATS)}")
    check_png_range(out, args, calib)
    color, depth, ply = _side_outputs(out, args)
    if color is not None and not color.lower().endswith((".png", ".jpg", ".jpeg", ".bmp")):
        raise InputError(f"{color}: the colour picture must be a .png/.jpg/.bmp file")
    sides = [p for p in (color, *_confidence_outputs(out, args), depth, ply) if p is not None]
    _check_outputs([*sides, out], args.force, (args.left, args.right))
    return Job(os.path.splitext(os.path.basename(out))[0], args.left, args.right, out, sides)


def run(args, single: bool) -> int:
    """``mccnn-cl match`` with ``--workers N`` (a LocalCluster) or ``--scheduler ADDRESS``."""
    from .batch import prepare
    from .cli.common import _hyperparameters, _load_weights, _range_request, _read_calibration, _say
    if args.workers is not None and args.scheduler is not None:
        raise InputError("give --workers N (a cluster on this machine) or --scheduler ADDRESS, not both")
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    request = _range_request(args)  # the options alone: before any file is read or a cluster starts
    check_split_tiles(args.split_tiles, *((0, "auto") if request == "auto" else request))
    settings = None
    if single:
        if getattr(args, "resume", False):
            raise InputError("--resume is for batches")
        calib = _read_calibration(args)  # Middlebury 2001-2006: the range only, no depth (a note)
        todo, skipped = [_single_job(args, calib)], []
        _load_weights(args)  # a bad weights file fails here, before any cluster starts
    else:
        todo, skipped, calib, _, settings = prepare(args)  # weights checked there
    limit = None
    if args.memory_limit is not None:
        if not args.memory_limit > 0:
            raise InputError(f"--memory-limit must be a positive number of MiB, got {args.memory_limit:g}")
        limit = int(args.memory_limit * 2**20)
    low, max_disp = batch_range(args, calib)
    config = matcher_config(args.cost, args.weights, args.device, limit, args.volume_dtype,
                            min_disparity=low, **_hyperparameters(args.hyper))
    want = args.confidence is not None or args.labels is not None
    summary = Summary(skipped=[j.name for j in skipped])
    folder = os.path.dirname(os.path.abspath(todo[0].out)) if single and todo else args.output_dir
    if todo:
        from distributed import Client
        cluster = local_cluster(args.workers) if args.workers is not None else None
        try:
            with Client(cluster if cluster is not None else args.scheduler) as client:
                _say(f"dask: {n_workers(client)} workers ({'local' if cluster else args.scheduler}), "
                     f"{len(todo)} pair(s)" + (f", {len(skipped)} complete, skipped" if skipped else ""))
                seen = 0

                def failed(job, exc, result=None):  # as the one-process batch: this pair fails, the batch goes on ...
                    if single:
                        raise exc
                    reason, bad = describe_failure(exc)
                    summary.failed.append((job.name, reason, bad))
                    stop = storage_stop(exc, job, folder, result is not None, left=len(todo) - seen,
                                        probe_bytes=_probe_size(result))
                    if stop is not None:  # ... unless no later pair can be written either (a full disk ...)
                        summary.report()
                        raise stop from exc
                    _say(f"{job.name}: failed: {reason}")

                for job, outcome in match_pairs(client, todo, config, max_disp, want,
                                                 split_tiles=True if args.split_tiles else None, progress=True):
                    seen += 1
                    if isinstance(outcome, BaseException):
                        failed(job, outcome)
                        continue
                    try:
                        write_pair(job, outcome, args, calib, settings)
                    except Exception as exc:  # noqa: BLE001
                        failed(job, exc, outcome)
                        continue
                    summary.done.append(job.name)
                    if args.verbose or single or outcome.auto is not None:  # an automatic range is always said
                        _say(f"{done_line(job, outcome)}, {outcome.where}")
        finally:
            if cluster is not None:
                cluster.close()
    if single:
        return 0
    summary.report()
    return summary.exit_status()
