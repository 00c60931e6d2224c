"""Kernel choices by measurement on the device at hand, kept in a per-device cache.

:data:`mccnn_cl.opencl.device.RULES` gives every device class a value of each
kernel choice, measured on one machine.  :func:`tune` measures the
candidates of the choices listed in :func:`options` on the device at hand,
at a representative size, and keeps for each the fastest candidate whose
output equals the rules' own (bit for bit, or to rounding for the paired SGM
sweeps, whose sums are ordered differently); a candidate that gives another
result, or fails, is never chosen.  The choices are stored in
``<cache>/tune/<hash>.json`` (:func:`mccnn_cl.opencl.binaries.cache_root`), keyed
by the platform (name, version), the device (name, driver version) and the
package version: a file of another device, driver or version is ignored.
Files are written to a temporary name and renamed, so two processes tuning
at once leave one whole file; a file that cannot be read is ignored with one
warning and rewritten by the next tuning.

Every :class:`~mccnn_cl.opencl.context.ClContext` loads its device's choices
(:meth:`DeviceProfile.rule <mccnn_cl.opencl.device.DeviceProfile.rule>` returns
them) unless ``MCCNN_TUNE=off``.  A device never tuned uses the rules: the
first use does not tune (``mccnn-cl tune`` does, in about a minute on 2 CPU
cores).  The choices tuned are the CPU-shaped paths' (devices of the
``cpu`` and ``llvmpipe`` columns); GPU-shaped devices keep the rules.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from .tune_cache import FORMAT, SIZE, cache_path, enabled, identity, load, store  # noqa: F401 (the cache, re-exported)

log = logging.getLogger(__name__)



@dataclass
class Option:
    """One kernel choice: ``candidates`` (each a dict of RULES rows to set),
    ``run(ctx) -> (seconds, output)`` the stage at the representative size
    under the candidate, ``exact``: outputs must be equal bit for bit (else
    to rounding)."""

    name: str
    candidates: list
    run: object
    exact: bool = True


def _inputs(ctx, size):
    H, W, D = size
    rng = np.random.default_rng(1234)
    img_l = rng.random((H, W), dtype=np.float32)
    img_r = np.roll(img_l, -5, axis=1)
    vol = rng.random((D, H, W), dtype=np.float32)
    vol[np.broadcast_to(np.arange(D)[:, None, None] > np.arange(W)[None, None, :], vol.shape)] = np.nan
    return img_l, img_r, vol


def _timed(ctx, fn, repeat):
    fn()
    ctx.finish()
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ctx.finish()
        best = min(best, time.perf_counter() - t)
    return best


def options(ctx, size=SIZE, repeat=3) -> list:
    """The choices tuned on ``ctx``'s device (none on GPU-shaped devices)."""
    if not ctx.profile.is_cpu:
        return []
    H, W, D = size
    img_l, img_r, vol = _inputs(ctx, size)
    d_l, d_r, d_vol = ctx.to_device(img_l), ctx.to_device(img_r), ctx.to_device(vol)
    out = ctx.empty(vol.nbytes, "tuning output")

    def sgm_run(ctx_):
        from ..stages.sgm import SGM

        sgm = SGM(ctx_)
        sec = _timed(ctx_, lambda: sgm(d_vol, d_l, d_r, D, H, W, out=out), repeat)
        return sec, ctx_.from_device(out, (D, H, W))

    def cbca_run(ctx_):
        from ..stages.cbca import CBCA
        from ..stages.cross import CrossArms, max_arm

        arm = max_arm(4)
        cross = CrossArms(ctx_)
        arms_l, arms_r = cross(d_l, H, W), cross(d_r, H, W)
        cbca = CBCA(ctx_)
        sec = _timed(ctx_, lambda: cbca(d_vol, arms_l, arms_r, D, H, W, 2, arm, out=out), repeat)
        return sec, ctx_.from_device(out, (D, H, W))

    def local_run(ctx_):
        from ..costs.census import CensusCost
        from ..stages.disparity import Subpixel, WinnerTakeAll

        cost, wta, sub = CensusCost(ctx_), WinnerTakeAll(ctx_), Subpixel(ctx_)
        h, w = H - 8, W - 8

        def go():
            cost(img_l, img_r, D, out=out)
            disp = wta.left(out, D, h, w)
            return sub(out, disp, D, h, w)

        sec = _timed(ctx_, go, repeat)
        return sec, ctx_.from_device(go(), (h, w))

    units = ctx.profile.compute_units
    opts = [
        Option("sgm_cols", [{"sgm_cols": c} for c in (32, 64, 128)], sgm_run),
        Option("sgm_paired", [{"sgm_paired_max_units": 0}, {"sgm_paired_max_units": max(units, 1)}], sgm_run,
               exact=False),
        Option("cbca_path", [{"cbca_fused": True, "cbca_multi": True}, {"cbca_fused": True, "cbca_multi": False},
                             {"cbca_fused": False, "cbca_multi": False}], cbca_run),
        Option("launch_local", [{"launch_local": list(t)} for t in ((64, 2, 2), (32, 4, 4), (16, 4, 4), (8, 8, 8),
                                                                    (128, 1, 1))], local_run),
    ]
    if ctx.profile.loop_limit is not None:  # llvmpipe: the paired sweeps refuse to run under its limit
        opts = [o for o in opts if o.name != "sgm_paired"]
    return opts


#: How much faster than the rules' candidate another must be to be chosen
#: (timings on a shared machine vary by a few per cent between runs).
MARGIN = 0.05


def _rules_value(profile, name):
    from .device import RULES

    v = RULES[name][profile.kind]
    return list(v) if isinstance(v, tuple) else v


def _same(a, b, exact) -> bool:
    if a.shape != b.shape:
        return False
    if exact:
        return np.array_equal(a, b, equal_nan=True)
    return bool(np.allclose(a, b, rtol=1e-5, atol=1e-5, equal_nan=True))


def choose(ctx, opts, progress=None, rounds=1) -> tuple:
    """Measure every candidate of every option (rules first: the reference
    output), ``rounds`` times in turn (candidate 1, 2, ..., 1, 2, ...: a
    change of the machine's load falls on all of them), the best time kept;
    returns ``(choices, measured)``: the RULES rows of the fastest correct
    candidate per option, and every candidate's seconds (None: wrong output
    in any round, or failed)."""
    profile = ctx.profile
    choices, measured = {}, {}
    for opt in opts:
        saved = dict(profile.tuned)
        try:
            profile.tuned.clear()
            profile.tuned.update({k: v for k, v in choices.items()})
            _, reference = opt.run(ctx)
            best = [float("inf")] * len(opt.candidates)
            for _ in range(max(1, int(rounds))):
                for j, cand in enumerate(opt.candidates):
                    if best[j] is None:
                        continue
                    profile.tuned.clear()
                    profile.tuned.update(choices)
                    profile.tuned.update(cand)
                    try:
                        sec, output = opt.run(ctx)
                        ok = _same(output, reference, opt.exact)
                    except Exception as exc:  # noqa: BLE001 - a candidate that fails is not chosen
                        log.info("tuning %s: candidate %s failed: %s", opt.name, cand, exc)
                        sec, ok = None, False
                    best[j] = min(best[j], sec) if ok else None
                    if progress is not None:
                        progress()
            results = list(zip(opt.candidates, best))
        finally:
            profile.tuned.clear()
            profile.tuned.update(saved)
        measured[opt.name] = [[c, s] for c, s in results]
        good = [(s, i) for i, (c, s) in enumerate(results) if s is not None]
        if good:
            fastest, i = min(good)
            rules = [j for j, (c, s) in enumerate(results) if s is not None
                     and all(_rules_value(profile, k) == v for k, v in c.items())]
            if rules and results[rules[0]][1] <= fastest * (1 + MARGIN):
                i = rules[0]  # the rules' own candidate unless another is clearly faster
            choices.update(results[i][0])
    return choices, measured


def tune(ctx, progress: bool = False, size=SIZE, rounds=3) -> tuple:
    """Tune ``ctx``'s device, store the choices, apply them to ``ctx.profile``;
    returns ``(choices, measured, path)``."""
    opts = options(ctx, size, repeat=1)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=rounds * sum(len(o.candidates) for o in opts), desc="tuning", unit="run")
    try:
        choices, measured = choose(ctx, opts, None if bar is None else (lambda: bar.update(1)), rounds)
    finally:
        if bar is not None:
            bar.close()
    path = store(ctx.device, choices, measured)
    ctx.profile.tuned.clear()
    ctx.profile.tuned.update(choices)
    return choices, measured, path
