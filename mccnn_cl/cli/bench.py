"""``mccnn-cl bench``: per-stage timings of one pair beside OpenCV SGBM, the
rate table and the memory plan (the machinery: :mod:`mccnn_cl.benchmark`)."""

from __future__ import annotations

import time

from ..benchmark import group_timings, rate_table, synthetic_pair
from ..errors import InputError


def run(args) -> int:
    """``mccnn-cl bench``: time each stage (best of ``--repeat`` runs after a
    warm-up) beside OpenCV SGBM, then the rate table and the memory plan."""
    from ..evaluation.baseline import sgbm
    from ..io import read_image
    from ..validate import check_pair, patch_size
    from . import commands
    from .common import parse_size
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
    matcher = commands._make_matcher(args, max_disp, weights)
    h, w = left.shape
    margin = int(matcher.margin)
    vol = max_disp * (h - 2 * margin) * (w - 2 * margin) * 4
    say(f"bench: {what}, {max_disp} disparities, cost {args.cost}"
        + (f" ({weights.num_parameters():,} weights)" if weights is not None else ""))
    say(f"device: {matcher.ctx.describe()}")
    ctx = matcher.ctx
    if not args.no_warmup:
        t0 = time.perf_counter()
        matcher.compute(left, right)  # warm-up: lazy kernel builds, first allocations
        t_warm = time.perf_counter() - t0
        say(f"set-up: kernels {ctx.build_seconds:.2f} s ({ctx.builds} builds, {ctx.binary_loads} stored "
            f"binaries); first call {t_warm:.2f} s, builds included (not in the times below)")
    runs = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        res = matcher.compute(left, right, timings=True)
        total = time.perf_counter() - t0
        runs.append((total, group_timings(res.timings), res.timings))
    total, groups, raw = min(runs, key=lambda r: r[0])
    base_times = [sgbm(left, right, max_disp, return_time=True)[1] for _ in range(args.repeat)]
    rest = total - sum(groups.values())
    say(f"{'stage':<28} {'seconds':>9} {'share':>7}")
    titles = {"cost": "matching cost (" + ("network" if args.cost == "cnn" else "census") + ")",
              "CBCA": "CBCA (arms + aggregation)", "SGM": "SGM", "rest": "the rest (WTA ... bilateral)"}
    for name, sec in groups.items():
        say(f"{titles[name]:<28} {sec:>9.3f} {sec / total:>7.1%}")
    say(f"{'(host, copies, untimed)':<28} {max(rest, 0.0):>9.3f} {max(rest, 0.0) / total:>7.1%}")
    say(f"{'total (' + ('MC-CNN' if args.cost == 'cnn' else 'census') + ' pipeline)':<28} {total:>9.3f}")
    say(f"{'OpenCV SGBM (same range)':<28} {min(base_times):>9.3f}")
    say(f"cost volume: {max_disp} x {h - 2 * margin} x {w - 2 * margin} float32 = {vol / 2**20:.0f} MiB each")
    rate_table(matcher, left.shape, groups, total, min(base_times), vol, say)
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
