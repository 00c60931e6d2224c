"""``mccnn-cl tune``: kernel choices by measurement (:mod:`mccnn_cl.opencl.tune`), then
the kernel binaries of the default method stored (:mod:`mccnn_cl.opencl.binaries`)."""

from __future__ import annotations

import time


def describe_choices(device) -> list:
    """Lines naming each tunable choice's value on ``device`` and where it comes from."""
    from ..opencl import tune
    from ..opencl.context import _cl
    from ..opencl.device import DeviceProfile

    profile = DeviceProfile.of(device, _cl())
    tuned = tune.load(device)
    if not tune.enabled():
        head = "kernel choices: the rules table (MCCNN_TUNE=off)"
    elif tuned:
        head = f"kernel choices: tuned on this device ({tune.cache_path(device)}), the rest from the rules table"
    elif tune.record(device) is not None:
        head = (f"kernel choices: tuned on this device ({tune.cache_path(device)}): no candidate beat the "
                "rules table's")
    else:
        head = "kernel choices: the rules table (not tuned: run `mccnn-cl tune`)"
    profile.tuned.update(tuned)
    lines = [head]
    names = ("sgm_paired_max_units", "sgm_cols", "sgm_width", "cbca_fused", "cbca_multi", "fst_volume_width", "wta_chunks",
             "mirror_lines", "launch_local")
    if not profile.is_cpu:  # the GPU-shaped paths and the GEMM tile are tuned there
        names = ("sgm_stage", "sgm_cols", "sgm_wg_cols", "cbca_workgroup", "launch_local", "network_gemm_tile")
    for name in names:
        value = profile.fst_volume_width() if name == "fst_volume_width" else profile.rule(name)
        lines.append(f"  {name:22s} {value!s:14s} ({profile.rule_source(name)})")
    if not profile.is_cpu:
        return lines
    tiles, mine = profile.network_tiles(), profile.tuned.get("network_tiles", {})
    for key, what in (("CONV_RM", "conv pixels per work-item"), ("CONV_RN", "fst conv channels per work-item"),
                      ("RM", "head cells per work-item")):
        label = f"network_tiles {key}"
        lines.append(f"  {label:22s} {tiles[key]!s:14s} ({'tuned' if key in mine else 'rules'}), {what}")
    return lines


def run(args) -> int:
    from ..opencl import tune
    from ..opencl.context import ClContext

    from ..errors import InputError
    from .common import parse_size

    size = tune.SIZE
    if getattr(args, "size", None):
        size = parse_size(args.size, 3, "96x1242x228", what="rows x columns x levels")
        if size[1] < 16:
            raise InputError(f"--size: 16 columns or more, got {args.size!r}")
    rounds = getattr(args, "rounds", 5)
    if rounds < 1:
        raise InputError(f"--rounds must be >= 1, got {rounds}")
    ctx = ClContext(args.device)
    print(f"tuning {ctx.describe()} at {'x'.join(map(str, size))} (rows x columns x levels), {rounds} rounds")
    t0 = time.perf_counter()
    choices, measured, path = tune.tune(ctx, progress=True, size=size, rounds=rounds)
    for name, res in measured.items():
        parts = []
        for cand, sec in res["candidates"]:
            label = " ".join(f"{k}={v}" for k, v in cand.items()) or "rules"
            parts.append(f"{label}: " + ("wrong/failed" if sec is None else f"{sec * 1e3:.1f} ms"))
        print(f"  {name} (noise {res['noise']:.0%}): " + "; ".join(parts))
    print(f"choices {choices or 'none (the rules table stands)'}\nwritten to {path} ({time.perf_counter() - t0:.0f} s)")
    if not args.no_binaries:
        from ..opencl import binaries

        if binaries.enabled():
            t1 = time.perf_counter()
            # a new context: the tuning's context already holds the programs it measured,
            # which would be reused unsaved (and it chose its tiles before the choices existed)
            bctx = ClContext(args.device)
            bctx.save_binaries = True
            from ..pipeline import StereoMatcher

            import numpy as np

            rng = np.random.default_rng(0)
            left = rng.random((40, 320), dtype=np.float32)
            right = np.roll(left, -3, axis=1)
            for cost in ("cnn", "census"):  # a small pair: the kernels built lazily too
                StereoMatcher(cost=cost, device=bctx).compute(left, right)
            print(f"kernel binaries of the default method stored under {binaries.cache_root()} "
                  f"({time.perf_counter() - t1:.0f} s)")
    return 0
