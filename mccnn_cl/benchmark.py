"""Benchmark machinery of ``mccnn-cl bench`` and ``tools/benchmarks/``: the per-stage table.

:data:`STAGE_GROUP` is the one mapping from :class:`~mccnn_cl.pipeline.StereoMatcher`'s
stage names (``StereoResult.timings`` keys) to the rows of the paper's runtime
table (matching cost, CBCA, SGM, the rest); :func:`group_timings` applies it,
and both the command line and ``tools/benchmarks/bench_pipeline.py`` read it.
:func:`synthetic_pair` is a textured pair with a slanted disparity field for
timing without data.  :func:`rate_table` sets each stage's time beside a
floor measured in the same run: the network's FLOP over numpy's float32 GEMM
rate on the host CPU (:func:`numpy_gemm_rate`; a floor only where the device
is that CPU, :func:`host_gemm_applies`), the volume stages' least traffic
over the device's buffer-copy bandwidth (:func:`copy_bandwidth`, timed by
OpenCL profiling events, :func:`device_seconds`), both counting reads +
writes (:func:`traffic_floor`); :func:`measure_baselines` and
:func:`compare_baselines` take them before and after the timed runs.
:mod:`mccnn_cl.cli.bench` is the ``bench`` sub-command that uses them.
"""

from __future__ import annotations

import time

import numpy as np


#: StereoResult.timings key -> group (every stage StereoMatcher times;
#: tests/test_bench.py checks that none is missing).  Names not listed go by
#: substring (:data:`_FALLBACK`), else to "rest".
STAGE_GROUP = {"C_CNN": "cost", "C_CNN_upload": "cost",
               "cross": "CBCA", "C_CBCA": "CBCA", "C": "CBCA", "C_SGM": "SGM",
               # the right reference (right_reference="aggregated"): the same stages again
               "cross_R": "CBCA", "C_R_SGM": "SGM", "C_R": "CBCA", "right_volume": "rest",
               **dict.fromkeys(("D_L", "D_R", "labels", "D_INT", "D_SE", "D_E", "D_median", "D_BF"), "rest")}
GROUPS = ("cost", "CBCA", "SGM", "rest")
_FALLBACK = (("cost", ("network", "cnn", "census", "conv")),
             ("CBCA", ("cbca", "cross", "aggregat")),
             ("SGM", ("sgm", "semiglobal")))


def stage_group(name: str) -> str:
    """The group of one stage name (see :data:`STAGE_GROUP`)."""
    group = STAGE_GROUP.get(name)
    if group is None:
        low = name.lower()
        group = next((g for g, keys in _FALLBACK if any(k in low for k in keys)), "rest")
    return group


def group_timings(timings: dict) -> dict:
    """Seconds per group: cost (matching cost), CBCA (cross arms + every aggregation), SGM, rest."""
    out = dict.fromkeys(GROUPS, 0.0)
    for name, sec in timings.items():
        out[stage_group(name)] += float(sec)
    return out


def synthetic_pair(width, height, max_disparity, seed=0):
    """A textured left image and a right image shifted by a slanted disparity field (uint8 gray)."""
    import cv2
    rng = np.random.default_rng(seed)
    noise = rng.random((height, width + max_disparity)).astype(np.float32)
    tex = cv2.GaussianBlur(noise, (0, 0), 1.5)
    tex = (tex - tex.min()) / max(float(np.ptp(tex)), 1e-6)
    big = (tex * 255).astype(np.uint8)
    left = big[:, max_disparity:].copy()
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    d = (0.15 + 0.6 * ys / max(height - 1, 1)) * (max_disparity - 1)
    # right(x) = left(x + d): sample the wide texture at x + d (+ the offset of `left`)
    right = cv2.remap(big, xs + d + max_disparity, ys, cv2.INTER_LINEAR)
    return left, right


#: numpy_gemm_rate's default shape: the paper head's (cells x 300) @ (300 x 300)
GEMM_SHAPE = (131072, 300)
#: a baseline measured before and after the timed runs that moved by more
#: than this fraction (max / min - 1) draws a warning
DRIFT_WARN = 0.15


def numpy_gemm_rate(n=GEMM_SHAPE[0], k=GEMM_SHAPE[1], repeat=3) -> float:
    """FLOP/s of numpy's float32 GEMM **on the host CPU** on the head's shape
    (n x k) @ (k x k), best of ``repeat`` after an untimed warm-up.  The
    product goes into one array kept across the runs (``np.matmul(a, b,
    out=c)``): a fresh n x k output per run (157 MB at the default shape)
    timed its page faults too, ~4 % of the GEMM, and flattered every ratio
    to this floor."""
    if int(repeat) < 1:
        raise ValueError(f"repeat must be >= 1, got {repeat}")
    rng = np.random.default_rng(0)
    a = rng.random((n, k), dtype=np.float32)
    b = rng.random((k, k), dtype=np.float32)
    c = np.empty((n, k), dtype=np.float32)
    np.matmul(a, b, out=c)  # warm-up: thread pool started, the output's pages mapped
    best = float("inf")
    for _ in range(int(repeat)):
        t0 = time.perf_counter()
        np.matmul(a, b, out=c)
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n * k * k / best


def device_seconds(ctx, enqueue, repeat=3, warmup=True, back_to_back=8):
    """(best seconds, how timed) of one device operation: ``enqueue(queue)``
    enqueues it on ``queue`` and returns its event.

    Timed by OpenCL profiling events on a queue of its own with
    ``PROFILING_ENABLE`` (``event.profile.end - event.profile.start``: the
    device's clock, no host wait in it).  Where the device refuses such a
    queue or reports no times, ``back_to_back`` operations are enqueued at
    once on ``ctx.queue`` and waited for with one blocking
    ``queue.finish()``: their wall time over ``back_to_back``.  Not through
    ``ctx.finish()``, whose helper thread and checks for Ctrl-C add a little
    host time to each wait.  Work queued on ``ctx.queue`` beforehand must
    be finished by the caller."""
    cl = ctx.cl
    try:
        queue = cl.CommandQueue(ctx.context, properties=cl.command_queue_properties.PROFILING_ENABLE)
    except cl.Error:
        queue = None
    if queue is not None:
        try:
            if warmup:
                enqueue(queue).wait()
            best = float("inf")
            for _ in range(int(repeat)):
                ev = enqueue(queue)
                ev.wait()
                best = min(best, (ev.profile.end - ev.profile.start) * 1e-9)
            if 0 < best < float("inf"):
                return best, "OpenCL profiling events"
        except cl.Error:
            pass
        finally:
            queue.finish()
    queue = ctx.queue
    queue.finish()
    if warmup:
        enqueue(queue)
        queue.finish()
    best = float("inf")
    for _ in range(int(repeat)):
        t0 = time.perf_counter()
        for _ in range(int(back_to_back)):
            enqueue(queue)
        queue.finish()
        best = min(best, (time.perf_counter() - t0) / int(back_to_back))
    return best, f"{int(back_to_back)} back to back, one blocking wait"


def copy_baseline(ctx, repeat=3, nbytes=None) -> dict:
    """A device buffer-to-buffer copy of ``nbytes`` (default 256 MiB, beyond
    any cache, or the max allocation if smaller), best of ``repeat`` after a
    warm-up, timed by :func:`device_seconds`: ``{"rate": bytes/s with the
    read and the write counted (2 nbytes / s), "seconds", "nbytes",
    "timer", "repeat"}``."""
    nbytes = int(min(256 << 20, ctx.max_alloc) if nbytes is None else nbytes)
    src, dst = ctx.empty(nbytes, "bench copy source"), ctx.empty(nbytes, "bench copy target")
    try:
        ctx.fill(src, 0.5, nbytes)  # real pages: an untouched buffer may read as the shared zero page
        ctx.fill(dst, 0.25, nbytes)
        ctx.finish()  # not timed
        sec, timer = device_seconds(
            ctx, lambda q: ctx.cl.enqueue_copy(q, dst, src, byte_count=nbytes), repeat)
    finally:
        src.release()
        dst.release()
    return {"rate": 2.0 * nbytes / sec, "seconds": sec, "nbytes": nbytes, "timer": timer, "repeat": int(repeat)}


def copy_bandwidth(ctx, repeat=3) -> float:
    """Bytes/s of a device buffer-to-buffer copy (read + write counted), best
    of ``repeat`` (:func:`copy_baseline`)."""
    return copy_baseline(ctx, repeat)["rate"]


def traffic_floor(nbytes, copy_bw) -> float:
    """Seconds to move ``nbytes`` of volume traffic at the copy rate: bench's
    one convention, both sides counted alike, the reads plus the writes a
    stage needs over :func:`copy_bandwidth` (which counts a copy's read and
    its write).  So one read of a volume V costs V / copy_bw, half a copy's
    time; a write-only pass likewise."""
    return float(nbytes) / float(copy_bw)


def host_gemm_applies(ctx) -> bool:
    """Whether numpy's GEMM, which runs on the host CPU, measures the device
    the network runs on: a CPU device (PoCL, Intel's CPU runtime, llvmpipe).
    On a GPU or an accelerator it does not, and bench gives the network no
    floor."""
    prof = getattr(ctx, "profile", None)
    if prof is not None and hasattr(prof, "is_cpu"):
        return bool(prof.is_cpu)
    return bool(int(ctx.device.type) & int(ctx.cl.device_type.CPU))


def volume_bytes(matcher, shape, max_disparity=None) -> int:
    """Bytes of one cost volume, D x (H - 2m) x (W - 2m) cells in the
    matcher's storage dtype (``vdtype``: 4 bytes per cell, 2 with float16)."""
    m = int(matcher.margin)
    D = int(matcher.max_disparity if max_disparity is None else max_disparity)
    return D * (int(shape[0]) - 2 * m) * (int(shape[1]) - 2 * m) * np.dtype(matcher.vdtype).itemsize


def stage_traffic(params, vol) -> dict:
    """Bytes each volume group moves at least (see :func:`rate_table`):
    {"CBCA", "SGM", "rest"} for Hyperparameters ``params`` and a volume of
    ``vol`` bytes."""
    nref = 2 if params.right_reference == "aggregated" else 1
    rounds = int(params.cbca_iterations > 0) + nref * int(params.cbca_iterations_after > 0)
    return {"CBCA": rounds * 2 * vol,
            "SGM": nref * 2 * vol,
            "rest": (2 * vol if nref == 2 else 0) + 2 * vol}


def floors(matcher, shape, vol, copy_bw, gemm=None) -> dict:
    """Seconds per group at the baselines: "cost" (the network's FLOP at
    ``gemm`` FLOP/s; only with the network and a GEMM rate) and "CBCA",
    "SGM", "rest" (:func:`stage_traffic` over ``copy_bw``,
    :func:`traffic_floor`)."""
    out = {name: traffic_floor(b, copy_bw) for name, b in stage_traffic(matcher.params, vol).items()}
    if matcher.cost_name == "cnn" and gemm is not None:
        out = {"cost": matcher.cost.flops(shape[0], shape[1], matcher.max_disparity)["total"] / gemm, **out}
    return out


def measure_baselines(ctx, gemm=True, repeat=3) -> dict:
    """The in-run baselines: ``{"copy": copy_baseline(...), "gemm": FLOP/s of
    numpy_gemm_rate or None}`` (``gemm=False``: not measured)."""
    return {"copy": copy_baseline(ctx, repeat), "gemm": numpy_gemm_rate(repeat=repeat) if gemm else None}


def _moved(a, b) -> float:
    return max(a, b) / min(a, b) - 1.0


def compare_baselines(before, after, load=(None, None), cores=None) -> tuple:
    """(chosen, lines): the better (higher) rate of each baseline measured
    before and after the timed runs (:func:`measure_baselines`), which is
    used for the floors, and the lines that say so; warnings when one moved
    by more than :data:`DRIFT_WARN` or the 1-min load average (``load``: at
    the start, at the end) exceeded ``cores``.  ``chosen``: {"copy": bytes/s,
    "gemm": FLOP/s or None, "copy_from": "before" | "after", "gemm_from",
    "warnings": [...]}."""
    cb, ca = before["copy"], after["copy"]
    chosen = {"copy": max(cb["rate"], ca["rate"]), "copy_from": "before" if cb["rate"] >= ca["rate"] else "after",
              "gemm": None, "gemm_from": None, "warnings": []}
    lines = [f"baselines before / after the timed runs (each the best of {cb['repeat']}; the floors use the "
             f"better):"]
    if before.get("gemm") is not None and after.get("gemm") is not None:
        gb, ga = before["gemm"], after["gemm"]
        chosen["gemm"], chosen["gemm_from"] = max(gb, ga), "before" if gb >= ga else "after"
        n, k = GEMM_SHAPE
        lines.append(f"  host CPU numpy float32 GEMM ({n} x {k}) @ ({k} x {k}): {gb / 1e9:.1f} / {ga / 1e9:.1f} "
                     f"GFLOP/s, using {chosen['gemm'] / 1e9:.1f} ({chosen['gemm_from']})")
        if _moved(gb, ga) > DRIFT_WARN:
            chosen["warnings"].append(f"warning: the GEMM baseline moved {_moved(gb, ga):.0%} between before and "
                                      f"after the timed runs (more than {DRIFT_WARN:.0%}): the machine's load "
                                      f"changed; the ratios are uncertain")
    lines.append(f"  device buffer copy of {cb['nbytes'] / 2**20:.0f} MiB (read + write counted; {cb['timer']}): "
                 f"{cb['rate'] / 1e9:.2f} / {ca['rate'] / 1e9:.2f} GB/s, using {chosen['copy'] / 1e9:.2f} "
                 f"({chosen['copy_from']})")
    if _moved(cb["rate"], ca["rate"]) > DRIFT_WARN:
        chosen["warnings"].append(f"warning: the copy baseline moved {_moved(cb['rate'], ca['rate']):.0%} between "
                                  f"before and after the timed runs (more than {DRIFT_WARN:.0%}): the machine's "
                                  f"load changed; the ratios are uncertain")
    if cores:
        high = [f"{w} {v:.2f}" for w, v in zip(("at the start", "at the end"), load) if v is not None and v > cores]
        if high:
            chosen["warnings"].append(f"warning: load average (1 min) above the {cores} cores ({', '.join(high)}): "
                                      f"other work shared the machine; the times and baselines are uncertain")
    return chosen, lines + chosen["warnings"]


def rate_table(matcher, shape, groups, total, sgbm_time, vol, say=print, copy_bw=None, gemm=None) -> dict:
    """Second table of ``bench``: each stage's achieved rate beside a baseline
    measured in this run, and its time over the floor that baseline implies
    (``copy_bw``, ``gemm``: the baselines; measured here when None).

    Network: FLOP (NetworkCost.flops) / numpy's float32 GEMM rate on the
    head's shape, on the host CPU: a floor only where the device is that CPU
    (:func:`host_gemm_applies`); on a GPU the network gets no ratio and the
    whole pipeline no floor.  CBCA, SGM, the rest: the volume traffic the
    method needs at least (V = one volume, in the matcher's dtype), over the
    device's buffer-copy bandwidth, both counting reads + writes
    (:func:`traffic_floor`): one read and one write of the D x H x W volume
    per CBCA round (its iterations can run in one pass, as the fused kernel
    does; a round of 0 iterations moves nothing): the left reference's two
    rounds and the right reference's round after SGM (its first round is the
    left one, shifted); per SGM call, per reference; the right-reference
    volume, read + write (the pipeline mirrors the cost volume in place and
    back, 4 V, to hold one volume less); each WTA, one read.

    Returns {"floors": seconds per group (:func:`floors`), "ratios": time /
    floor per group, "stereo_floor", "pipeline_floor" (None without one),
    "pipeline_ratio", "copy_bw", "gemm", "gemm_on_device"}."""
    cnn = matcher.cost_name == "cnn"
    on_device = host_gemm_applies(matcher.ctx)
    if copy_bw is None:
        copy_bw = copy_bandwidth(matcher.ctx)
    if cnn and on_device and gemm is None:
        gemm = numpy_gemm_rate()
    traffic = stage_traffic(matcher.params, vol)
    fl = floors(matcher, shape, vol, copy_bw, gemm if on_device else None)
    rows = []
    if cnn:
        flop = matcher.cost.flops(shape[0], shape[1], matcher.max_disparity)["total"]
        t = groups["cost"]
        if on_device:
            rows.append(("matching cost (network)", f"{flop / t / 1e9:.1f} GFLOP/s",
                         f"host CPU numpy GEMM {gemm / 1e9:.1f} GFLOP/s", t / fl["cost"]))
        else:
            rows.append(("matching cost (network)", f"{flop / t / 1e9:.1f} GFLOP/s", "none (GEMM on host CPU)", None))
    stereo_t = stereo_b = 0.0
    for name, title in (("CBCA", "CBCA (arms + aggregation)"), ("SGM", "SGM"), ("rest", "the rest (WTA ... bilateral)")):
        t, b = groups[name], traffic[name]
        stereo_t, stereo_b = stereo_t + t, stereo_b + b
        got = f"{b / t / 1e9:.2f} GB/s ({b / vol:.0f} V)" if t > 0 else f"- ({b / vol:.0f} V)"
        rows.append((title, got, f"copy {copy_bw / 1e9:.2f} GB/s", t / fl[name] if b > 0 else None))
    stereo_floor = traffic_floor(stereo_b, copy_bw)
    rows.append(("stereo method (after cost)", f"{stereo_b / stereo_t / 1e9:.2f} GB/s ({stereo_b / vol:.0f} V)",
                 f"copy {copy_bw / 1e9:.2f} GB/s", stereo_t / stereo_floor))
    say("rates beside baselines measured in this run (V = one volume read or written; GB/s and the copy rate "
        "both count reads + writes; ratio = time / floor):")
    say(f"{'stage':<28} {'achieved':>24} {'baseline':>34} {'ratio':>8}")
    for title, got, base, ratio in rows:
        say(f"{title:<28} {got:>24} {base:>34} " + (f"{ratio:>7.2f}x" if ratio is not None else f"{'-':>8}"))
    floor = pipe_ratio = None
    if cnn and not on_device:
        say(f"{'whole pipeline':<28} {'no floor':>24} {'network: no device GEMM':>34} {'-':>8}")
        say("(numpy's GEMM runs on the host CPU, not on this device: the network has no floor here; the stereo "
            "method's row above is the part with one)")
    else:
        floor = sum(fl.values())
        pipe_ratio = total / floor
        what = "FLOP / host GEMM + traffic / copy" if cnn else "volume traffic / copy"
        say(f"{'whole pipeline':<28} {f'floor {floor:.3f} s':>24} {what:>34} {pipe_ratio:>7.2f}x")
    say(f"{'whole pipeline vs SGBM':<28} {f'{total:.3f} s':>24} {f'OpenCV SGBM {sgbm_time:.3f} s':>34} "
        f"{total / sgbm_time:>7.1f}x")
    ratios = {name: groups[name] / sec for name, sec in fl.items() if sec > 0}
    return {"floors": fl, "ratios": ratios, "stereo_floor": stereo_floor, "pipeline_floor": floor,
            "pipeline_ratio": pipe_ratio, "copy_bw": copy_bw, "gemm": gemm if on_device else None,
            "gemm_on_device": on_device}
