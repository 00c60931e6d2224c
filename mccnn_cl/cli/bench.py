"""``mccnn-cl bench``: per-stage timings of one pair beside OpenCV SGBM, the
rate table and the memory plan (the machinery: :mod:`mccnn_cl.benchmark`)."""

from __future__ import annotations

import os
import time

from ..benchmark import (compare_baselines, group_timings, host_gemm_applies, measure_baselines, rate_table,
                         synthetic_pair, volume_bytes)
from ..errors import InputError


def _load():
    """The 1-min load average (None where the system gives none)."""
    try:
        return os.getloadavg()[0]
    except (OSError, AttributeError):
        return None


def _load_text(load) -> str:
    return "unknown" if load is None else f"{load:.2f}"


def run(args) -> int:
    """``mccnn-cl bench``: time each stage (the run of best total of
    ``--repeat`` after a warm-up) beside OpenCV SGBM (best of ``--repeat``),
    then the rate table over baselines measured before and after the timed
    runs, and the memory plan."""
    from ..evaluation.baseline import sgbm
    from ..io import read_image
    from ..validate import check_pair, patch_size
    from . import commands
    from .common import counted, parse_size
    say = commands._say
    commands._positive("--max-disp", args.max_disp)
    commands._positive("--repeat", args.repeat)
    max_disp = args.max_disp or 228
    if args.left or args.right:
        if not (args.left and args.right):
            raise InputError("bench needs both --left and --right (or neither for a synthetic pair)")
        left, right = commands._gray(read_image(args.left)), commands._gray(read_image(args.right))
        what = f"{args.left} / {args.right}"
    else:
        w, h = parse_size(args.size, 2, "1242x375", what="width x height")
        left, right = synthetic_pair(w, h, max_disp)
        what = f"synthetic textured pair {w}x{h}"
    weights = commands._load_weights(args)
    check_pair(left, right, max_disp, patch_size(weights))
    cores, load_start = os.cpu_count(), _load()
    matcher = commands._make_matcher(args, max_disp, weights)
    h, w = left.shape
    margin = int(matcher.margin)
    vdtype = matcher.vdtype
    vol = volume_bytes(matcher, left.shape, max_disp)  # in the volumes' dtype (float16: 2 bytes a cell)
    say(f"bench: {what}, {max_disp} disparities, cost {args.cost}"
        + (f" ({weights.num_parameters():,} weights)" if weights is not None else ""))
    say(f"device: {matcher.ctx.describe()}")
    say(f"host: {cores} cores, load average (1 min) {_load_text(load_start)} at the start")
    ctx = matcher.ctx
    if not args.no_warmup:
        t0 = time.perf_counter()
        matcher.compute(left, right)  # warm-up: lazy kernel builds, first allocations
        t_warm = time.perf_counter() - t0
        say(f"set-up: kernels {ctx.build_seconds:.2f} s ({counted(ctx.builds, 'build')}, "
            f"{counted(ctx.binary_loads, 'stored binary', 'stored binaries')}); first call {t_warm:.2f} s, builds "
            "included (not in the times below)")
    # numpy's GEMM runs on the host CPU: a floor for the network only on a CPU device
    gemm = matcher.cost_name == "cnn" and host_gemm_applies(ctx)
    before = measure_baselines(ctx, gemm)
    builds, build_s = ctx.builds + ctx.binary_loads, ctx.build_seconds
    runs = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        res = matcher.compute(left, right, timings=True)
        total = time.perf_counter() - t0
        runs.append((total, group_timings(res.timings), res.timings))
    made, made_s = ctx.builds + ctx.binary_loads - builds, ctx.build_seconds - build_s
    total, groups, raw = min(runs, key=lambda r: r[0])
    base_times = [sgbm(left, right, max_disp, return_time=True)[1] for _ in range(args.repeat)]
    after = measure_baselines(ctx, gemm)
    load_end = _load()
    rest = total - sum(groups.values())
    say(f"times: the run with the best total of {args.repeat} timed run(s)"
        + (", after a warm-up" if not args.no_warmup else ", no warm-up (builds and first touches included)")
        + f"; OpenCV SGBM: best of {args.repeat}")
    say(f"{'stage':<28} {'seconds':>9} {'share':>7}")
    titles = {"cost": "matching cost (" + ("network" if args.cost == "cnn" else "census") + ")",
              "CBCA": "CBCA (arms + aggregation)", "SGM": "SGM", "rest": "the rest (WTA ... bilateral)"}
    for name, sec in groups.items():
        say(f"{titles[name]:<28} {sec:>9.3f} {sec / total:>7.1%}")
    say(f"{'(host, copies, untimed)':<28} {max(rest, 0.0):>9.3f} {max(rest, 0.0) / total:>7.1%}")
    say(f"{'total (' + ('MC-CNN' if args.cost == 'cnn' else 'census') + ' pipeline)':<28} {total:>9.3f}")
    say(f"{'OpenCV SGBM (same range)':<28} {min(base_times):>9.3f}")
    say(f"programs made during the timed runs: {made} ({made_s:.2f} s, inside the times above)")
    say(f"cost volume: {max_disp} x {h - 2 * margin} x {w - 2 * margin} {vdtype.name} = "
        f"{vol / 2**20:.{0 if vol >= 10 * 2**20 else 1}f} MiB each")
    say(f"host: {cores} cores, load average (1 min) {_load_text(load_start)} at the start, "
        f"{_load_text(load_end)} at the end")
    chosen, lines = compare_baselines(before, after, (load_start, load_end), cores)
    for line in lines:
        say(line)
    if matcher.cost_name == "cnn" and not gemm:
        say("  numpy's GEMM (host CPU) not measured: the device is not the host CPU, so the network has no floor")
    rate_table(matcher, left.shape, groups, total, min(base_times), vol, say,
               copy_bw=chosen["copy"], gemm=chosen["gemm"])
    plan = res.plan
    say(f"device memory: peak {res.peak_device_bytes / 2**20:.0f} MiB measured (buffers held at once), "
        f"{plan.peak_bytes / 2**20:.0f} MiB planned, limit {plan.budget / 2**20:.0f} MiB; "
        f"device {matcher.ctx.global_mem / 2**20:.0f} MiB, max allocation {matcher.ctx.max_alloc / 2**20:.0f} MiB")
    if plan.tiled:
        say(f"tiles: {plan.describe()}")
    else:
        say(f"tiles: none (the whole image at once: {plan.volumes} volumes)")
    if args.verbose:
        for name, sec in raw.items():
            say(f"  {name:<26} {float(sec):>9.4f}")
    return 0
