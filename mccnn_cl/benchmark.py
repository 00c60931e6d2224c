"""Benchmark machinery of ``mccnn-cl bench`` and ``tools/benchmarks/``: the per-stage table.

:data:`STAGE_GROUP` is the one mapping from :class:`~mccnn_cl.pipeline.StereoMatcher`'s
stage names (``StereoResult.timings`` keys) to the rows of the paper's runtime
table (matching cost, CBCA, SGM, the rest); :func:`group_timings` applies it,
and both the command line and ``tools/benchmarks/bench_pipeline.py`` read it.
:func:`synthetic_pair` is a textured pair with a slanted disparity field for
timing without data.  :func:`rate_table` sets each stage's time beside a
floor measured in the same run: the network's FLOP over numpy's float32 GEMM
rate (:func:`numpy_gemm_rate`), the volume stages' least traffic over the
device's buffer-copy bandwidth (:func:`copy_bandwidth`).  :mod:`mccnn_cl.cli.bench` is
the ``bench`` sub-command that uses them.
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


def numpy_gemm_rate(n=131072, k=300, repeat=3) -> float:
    """FLOP/s of numpy's float32 GEMM on the head's shape (n x k) @ (k x k), best of ``repeat``."""
    rng = np.random.default_rng(0)
    a = rng.random((n, k), dtype=np.float32)
    b = rng.random((k, k), dtype=np.float32)
    a @ b  # warm-up (thread pool start)
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n * k * k / best


def copy_bandwidth(ctx, repeat=3) -> float:
    """Bytes/s of a device buffer-to-buffer copy (read + write counted), best of
    ``repeat``, of 256 MiB (beyond any cache) or the max allocation if smaller."""
    nbytes = int(min(256 << 20, ctx.max_alloc))
    src, dst = ctx.empty(nbytes, "bench copy source"), ctx.empty(nbytes, "bench copy target")
    ctx.fill(src, 0.5, nbytes)  # real pages: an untouched buffer may read as the shared zero page
    ctx.fill(dst, 0.25, nbytes)
    ctx.cl.enqueue_copy(ctx.queue, dst, src, byte_count=nbytes)
    ctx.finish()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        ctx.cl.enqueue_copy(ctx.queue, dst, src, byte_count=nbytes)
        ctx.finish()
        best = min(best, time.perf_counter() - t0)
    src.release()
    dst.release()
    return 2.0 * nbytes / best


def rate_table(matcher, shape, groups, total, sgbm_time, vol, say=print):
    """Second table of ``bench``: each stage's achieved rate beside a baseline
    measured in this run, and its time over the floor that baseline implies.

    Network: FLOP (NetworkCost.flops) / numpy's float32 GEMM rate on the
    head's shape.  CBCA, SGM, the rest: the volume traffic the method needs
    at least, over the device's buffer-copy bandwidth: one read and one
    write of the D x H x W volume per CBCA round (its iterations can run in
    one pass, as the fused kernel does; a round of 0 iterations moves
    nothing): the left reference's two rounds and the right reference's
    round after SGM (its first round is the left one, shifted); per SGM
    call, per reference; the right-reference volume, read + write (the pipeline
    mirrors the cost volume in place and back, 4 V, to hold one volume less); each
    WTA, one read."""
    p = matcher.params
    nref = 2 if p.right_reference == "aggregated" else 1
    copy_bw = copy_bandwidth(matcher.ctx)
    rounds = int(p.cbca_iterations > 0) + nref * int(p.cbca_iterations_after > 0)
    traffic = {"CBCA": rounds * 2 * vol,
               "SGM": nref * 2 * vol,
               "rest": (2 * vol if nref == 2 else 0) + 2 * vol}
    rows, floor = [], 0.0
    if matcher.cost_name == "cnn":
        gemm = numpy_gemm_rate()
        flop = matcher.cost.flops(shape[0], shape[1], matcher.max_disparity)["total"]
        t = groups["cost"]
        rows.append(("matching cost (network)", f"{flop / t / 1e9:.1f} GFLOP/s", f"numpy GEMM {gemm / 1e9:.1f} GFLOP/s",
                     t / (flop / gemm)))
        floor += flop / gemm
    stereo_t = stereo_b = 0.0
    for name, title in (("CBCA", "CBCA (arms + aggregation)"), ("SGM", "SGM"), ("rest", "the rest (WTA ... bilateral)")):
        t, b = groups[name], traffic[name]
        stereo_t, stereo_b = stereo_t + t, stereo_b + b
        rows.append((title, f"{b / t / 1e9:.2f} GB/s ({b / vol:.0f} V)", f"copy {copy_bw / 1e9:.2f} GB/s",
                     t / (b / copy_bw) if b > 0 else None))
    rows.append(("stereo method (after cost)", f"{stereo_b / stereo_t / 1e9:.2f} GB/s ({stereo_b / vol:.0f} V)",
                 f"copy {copy_bw / 1e9:.2f} GB/s", stereo_t / (stereo_b / copy_bw)))
    floor += stereo_b / copy_bw
    say("rates beside baselines measured in this run (V = one volume read or written; ratio = time / floor):")
    say(f"{'stage':<28} {'achieved':>24} {'baseline':>26} {'ratio':>8}")
    for title, got, base, ratio in rows:
        say(f"{title:<28} {got:>24} {base:>26} " + (f"{ratio:>7.2f}x" if ratio is not None else f"{'-':>8}"))
    what = "network FLOP / GEMM + volume traffic / copy" if matcher.cost_name == "cnn" else "volume traffic / copy"
    say(f"{'whole pipeline':<28} {f'floor {floor:.3f} s':>24} {what:>26} {total / floor:>7.2f}x")
    say(f"{'whole pipeline vs SGBM':<28} {f'{total:.3f} s':>24} {f'OpenCV SGBM {sgbm_time:.3f} s':>26} "
        f"{total / sgbm_time:>7.1f}x")
