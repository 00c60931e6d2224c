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
first use does not tune (``mccnn-cl tune`` does: on 2 CPU cores about a
minute, the first run on a device ~2 minutes, most of the extra compiling).  On devices of the ``cpu`` and ``llvmpipe`` columns the choices tuned
are the CPU-shaped paths' sizes; on the others (GPUs) each GPU-shaped path
(SGM's and CBCA's work-groups) is measured against the CPU-shaped one it
replaces, with the conv GEMM's tile and the work-group size left to
``launch_local``.
"""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass

import numpy as np

from .tune_cache import FORMAT, SIZE, cache_path, enabled, identity, load, record, store  # noqa: F401 (the cache, re-exported)

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


#: A candidate's timed runs in one round last at least this long (a few milliseconds'
#: run is timed several times, so a scheduler hiccup does not decide for it), and at most
#: MAX_RUNS of them
LEAST_SECONDS = 0.1
MAX_RUNS = 20


#: A context manager factory around each candidate's timed runs (not its warm-up run,
#: which builds what it needs): ``mccnn-cl tune`` pauses its background build of the
#: default method's programs there (:func:`mccnn_cl.cli.tune.start_prebuild`).
quiet = contextlib.nullcontext


def _timed(ctx, fn, repeat):
    """Best time of ``fn`` (queue finished) after a warm-up: ``repeat`` runs, more
    while they add up to less than :data:`LEAST_SECONDS` (at most :data:`MAX_RUNS`),
    inside :data:`quiet`."""
    fn()
    ctx.finish()
    best, spent, runs = float("inf"), 0.0, 0
    with quiet():
        while runs < max(1, int(repeat)) or (spent < LEAST_SECONDS and runs < MAX_RUNS):
            t = time.perf_counter()
            fn()
            ctx.finish()
            dt = time.perf_counter() - t
            best, spent, runs = min(best, dt), spent + dt, runs + 1
    return best


def options(ctx, size=SIZE, repeat=1) -> list:
    """The choices tuned on ``ctx``'s device: the CPU-shaped paths' sizes on CPU-shaped
    devices (:func:`_cpu_options`), the GPU-shaped paths against the CPU-shaped ones and
    their sizes on the others (:func:`_gpu_options`)."""
    H, W, D = size
    img_l, img_r, vol = _inputs(ctx, size)
    d_l, d_r, d_vol = ctx.to_device(img_l), ctx.to_device(img_r), ctx.to_device(vol)
    del vol
    out = ctx.empty(4 * D * H * W, "tuning output")

    def sgm_run(ctx_):
        from ..stages.sgm_select import make_sgm

        sgm = make_sgm(ctx_)
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
        # the stages after SGM that leave their work-group size to launch_local
        from ..stages.disparity import Subpixel, WinnerTakeAll

        wta, sub = WinnerTakeAll(ctx_), Subpixel(ctx_)

        def go():
            disp = wta.left(d_vol, D, H, W)
            return sub(d_vol, disp, D, H, W)

        sec = _timed(ctx_, go, repeat)
        return sec, ctx_.from_device(go(), (H, W))

    d_mir = []

    def mirror_copy(ctx_):
        if not d_mir:
            d_mir.append(ctx_.empty(4 * D * H * W, "tuning mirror volume"))
            ctx_.cl.enqueue_copy(ctx_.queue, d_mir[0], d_vol)
        return d_mir[0]

    def mirror_run(ctx_):
        # the right reference's in-place mirroring, there and back, around its left WTA (on a copy of
        # the volume: a wrong candidate changes its map, and no other run's input)
        from ..stages.disparity import RightReference, WinnerTakeAll

        mir = mirror_copy(ctx_)
        rr, wta = RightReference(ctx_), WinnerTakeAll(ctx_)

        def go():
            rr.volume(mir, D, H, W)
            disp = wta.left(mir, D, H, W)
            rr.volume(mir, D, H, W)
            return disp

        sec = _timed(ctx_, go, repeat)
        return sec, ctx_.from_device(go(), (H, W), np.int32)

    def right_sgm_run(ctx_):
        # the right reference's SGM: the paired sweeps reading the volume mirrored, or the volume
        # mirrored in place around a plain SGM and back (on a copy of the volume, as mirror_run)
        from ..stages.disparity import RightReference
        from ..stages.sgm_select import make_sgm

        mir = mirror_copy(ctx_)
        sgm, rr = make_sgm(ctx_), RightReference(ctx_)

        def go():
            if sgm.reads_mirrored:
                sgm(mir, d_l, d_r, D, H, W, out=out, mirror=True)
            else:
                rr.volume(mir, D, H, W)
                sgm(mir, d_l, d_r, D, H, W, out=out)
                rr.volume(mir, D, H, W)

        sec = _timed(ctx_, go, repeat)
        return sec, ctx_.from_device(out, (D, H, W))

    def conv_run(ctx_):
        # the default network's conv stack (the network's larger share) on one image of the size
        from ..costs.features import ConvStack, default_tiles
        from ..weights import Weights

        weights = Weights.load()
        tiles = default_tiles(ctx_)
        stack = ConvStack(ctx_, weights, int(tiles["CONV_RN"]), int(tiles["CONV_RM"]))  # the fst stack's tile
        d_img = ctx_.to_device(np.ascontiguousarray(img_l[:, :, None]))
        feat = []

        def go():
            if feat:
                stack.give(feat.pop())
            feat.append(stack(d_img, H, W))

        sec = _timed(ctx_, go, repeat)
        h, w = H - stack.patch + 1, W - stack.patch + 1
        out_map = ctx_.from_device(feat[0], (h * w, stack.stride))
        stack.release_buffers()
        return sec, out_map

    host_feats = []

    def volume_run(ctx_):
        # fst's cosine volume (the pairs form) from planar features of the default network's maps
        from ..costs.fst import PADL, FstCost
        from ..models import resolve

        cost = FstCost(ctx_, resolve("general-fst"))
        wp = cost._wp(W)
        if not host_feats:  # made once (0.35 s), uploaded each run
            rng = np.random.default_rng(7)
            for _ in range(2):
                f = np.zeros((H, cost.nk, wp), np.float32)
                f[:, :, PADL:PADL + W] = rng.standard_normal((H, cost.nk, W), dtype=np.float32)
                host_feats.append(f)
        feats = [ctx_.to_device(f) for f in host_feats]
        sec = _timed(ctx_, lambda: cost.launch_volume(feats[0], feats[1], out, H, W, 0, D, H), repeat)
        got = ctx_.from_device(out, (D, H, W))
        for f in feats:
            f.release()
        return sec, got

    def head_run(ctx_):
        # the fully connected head of the shipped paper network (general-paper), whose cells per
        # second do not depend on the image's size: a small pair, HEAD_SIZE
        from ..costs.registry import make_cost
        from ..models import resolve

        h, w, d = (min(a, b) for a, b in zip(HEAD_SIZE, (H, W, D)))  # no larger than the tuning size
        cost = make_cost(ctx_, resolve("general-paper"))
        left = np.ascontiguousarray(img_l[:h, :w] * np.float32(255))
        right = np.ascontiguousarray(img_r[:h, :w] * np.float32(255))
        vh, vw = h - cost.patch + 1, w - cost.patch + 1  # the volume's domain (patch centres)
        buf = ctx_.empty(4 * d * vh * vw, "tuning head output")
        sec = _timed(ctx_, lambda: cost(left, right, d, out=buf), repeat)
        got = ctx_.from_device(buf, (d, vh, vw))
        buf.release()
        return sec, got

    runs = dict(sgm=sgm_run, cbca=cbca_run, local=local_run, conv=conv_run, volume=volume_run, head=head_run,
                mirror=mirror_run, right_sgm=right_sgm_run)
    return _cpu_options(ctx, runs) if ctx.profile.is_cpu else _gpu_options(ctx, runs)


def _launch_local(run):
    return Option("launch_local", [{"launch_local": list(t)} for t in ((64, 2, 2), (32, 4, 4), (16, 4, 4), (8, 8, 8),
                                                                       (128, 1, 1))], run)


def _gpu_options(ctx, runs) -> list:
    """GPU-shaped devices: each GPU-shaped path (the rules' gpu column) against the
    CPU-shaped one it replaces, the work-group SGM's columns per group, and the conv
    GEMM's tile.  Every candidate computes
    the rules' result (SGM to rounding: the one-direction kernels sum in the work-group
    path's order, the tiles and CBCA's short passes bit for bit)."""
    return [
        Option("sgm", [{"sgm_stage": "lines", "sgm_paired_max_units": 0, "sgm_cols": c} for c in (32, 64, 128)],
               runs["sgm"], exact=False),
        # the work-group stage's vertical paths, adjacent columns per work-group (bit for bit)
        Option("sgm_wg_cols", [{"sgm_wg_cols": c} for c in (8, 16, 32)], runs["sgm"]),
        Option("cbca_path", [{"cbca_workgroup": False}], runs["cbca"]),
        Option("network_gemm", [{"network_gemm_tile": t} for t in (dict(TM=128, RM=8), dict(TM=32, RM=2),
                                                                   dict(TN=32, RN=2), dict(TK=32))], runs["conv"]),
        _launch_local(runs["local"]),
    ]


def _cpu_options(ctx, runs) -> list:
    """CPU-shaped devices: SGM's sweeps, column width and vector width, CBCA's kernels, the register
    tiles of the conv stack and of the head, the fst volume's vector width, the left
    WTA's chunks per work-item, the right reference's mirroring and whether its SGM
    reads the volume mirrored, the work-group size left to launch_local."""
    units = max(ctx.profile.compute_units, 1)
    # SGM: the paired sweeps (their chunk width is fixed), or the one-direction
    # kernels at each column width (without paired sweeps the width matters).
    # Where the rules take the paired sweeps (a device of few units), the one-direction
    # kernels are tried at 32 columns only: their fastest width on every such CPU measured,
    # and still 1.6-2.4x the paired sweeps' time there; 64 and 128 columns cost a first
    # tune ~25 s of compiling on a 2-core Zen 3 (sgm_columns at 128 alone 15 s)
    widths = (32,) if units <= _rules_value(ctx.profile, "sgm_paired_max_units") else (32, 64, 128)
    sgm = [{"sgm_paired_max_units": units}] + [{"sgm_paired_max_units": 0, "sgm_cols": c} for c in widths]
    opts = [
        Option("sgm", sgm, runs["sgm"], exact=False),
        # sgm.cl on 16- or 8-wide vectors (rules: the device's vector width; the same bits)
        Option("sgm_width", [{"sgm_width": v} for v in (16, 8)], runs["sgm"]),
        Option("cbca_path", [{"cbca_fused": True, "cbca_multi": True}, {"cbca_fused": True, "cbca_multi": False},
                             {"cbca_fused": False, "cbca_multi": False}], runs["cbca"]),
        # the 3 x 3 layers by Winograd's F(2x2, 3x3) at each register block (RT, XA), or the direct
        # GEMM (None): the same features to float32 rounding (sums ordered differently).  [6, 1]:
        # 12 accumulators of 8 floats, AVX2's 16 registers nearly full (a 64 -> 64 layer on a Zen 3
        # 111 against 123 ms at [4, 1]; an acrt-shaped stack 1.46 against 1.90 s; BENCHMARKS.md)
        Option("network_winograd", [{"network_winograd": v} for v in ([4, 4], [4, 2], [4, 1], [6, 1], None)],
               runs["conv"], exact=False),
        # CONV_RN 8: a device that reports 8-wide vectors (the rules take 16 on CPUs)
        Option("network_conv", [{"network_tiles": {"CONV_RM": r}} for r in (4, 6, 8)]
               + [{"network_tiles": {"CONV_RN": 8, "CONV_RM": 8}}], runs["conv"]),
        # the fst volume's pairs form on 16- or 8-wide vectors (rules: the device's vector width)
        Option("fst_volume", [{"fst_volume_width": v} for v in (16, 8)], runs["volume"]),
        Option("network_head", [{"network_tiles": {"RM": r}} for r in (4, 8)], runs["head"]),
        # the left WTA's 16-pixel chunks per work-item (its map is the same at any)
        Option("wta_chunks", [{"wta_chunks": c} for c in (1, 4, 8, 16)], runs["local"]),
        # the right reference's mirroring: a work-item per line or per 16-pair block (the same bits)
        Option("mirror_lines", [{"mirror_lines": v} for v in (True, False)], runs["mirror"]),
        # the right reference's SGM reading the volume mirrored, or the volume mirrored in place
        # around it (the same bits; after mirror_lines, whose choice the second form uses)
        Option("sgm_mirror_reads", [{"sgm_mirror_reads": v} for v in (True, False)], runs["right_sgm"]),
        _launch_local(runs["local"]),
    ]
    if ctx.profile.loop_limit is not None:  # llvmpipe: the paired sweeps refuse to run under its limit
        opts[0].candidates = opts[0].candidates[1:]
    return opts


#: (rows, columns, levels) of the head's option: the paper network's head costs ~0.5 MFLOP per cell,
#: so the tuning size would take seconds per run.  At 16 x 400 x 32 (8 rows of 392 patch centres,
#: 100 k cells) a run takes ~0.6 s on a 2-core Zen 3 and the tiles compare as at 24 x 400 x 64
#: (RM 4 / RM 8: 0.806 / 0.593 s against 2.966 / 2.224 s), which took 45 of a tune's 100 s; fewer
#: rows (12) crowd the tiles' difference (0.371 / 0.339 s)
HEAD_SIZE = (16, 400, 32)

#: The least relative margin by which a candidate must beat the rules' own
#: to replace it, whatever the measured noise.
MARGIN = 0.03


def _merge(tuned: dict, cand: dict) -> None:
    """Apply a candidate's rows to ``tuned``: a tile row (a dict) adds its sizes
    to the sizes already tuned in that row (several options tune one row, each
    its own sizes), other rows are replaced."""
    for k, v in cand.items():
        if isinstance(v, dict) and isinstance(tuned.get(k), dict):
            tuned[k] = {**tuned[k], **v}
        else:
            tuned[k] = v


def _rules_value(profile, name):
    """The value the device gets untuned (the rules' column; for the network tiles, as
    :meth:`~mccnn_cl.opencl.device.DeviceProfile.network_tiles` adjusts it to the device)."""
    from dataclasses import replace

    v = replace(profile, tuned={}).value(name)
    return list(v) if isinstance(v, tuple) else v


def _is_rules(profile, cand) -> bool:
    """The candidate sets every row (every size of a tile row) to the rules' own value (the rules' choice)."""
    def same(k, v):
        base = _rules_value(profile, k)
        if isinstance(v, dict) and isinstance(base, dict):
            return all(base.get(kk) == vv for kk, vv in v.items())
        return base == (list(v) if isinstance(v, tuple) else v)
    return all(same(k, v) for k, v in cand.items())


def _candidates(profile, opt) -> list:
    """The candidates measured for ``opt``: the rules' choice ``{}`` first, then
    every other one (those equal to the rules' choice dropped)."""
    return [{}] + [c for c in opt.candidates if c and not _is_rules(profile, c)]


def _same(a, b, exact) -> bool:
    if a.shape != b.shape:
        return False
    bits = {1: np.uint8, 2: np.uint16, 4: np.uint32, 8: np.uint64}.get(a.dtype.itemsize)
    if (a.dtype == b.dtype and bits is not None and a.flags.c_contiguous and b.flags.c_contiguous
            and np.array_equal(a.view(bits), b.view(bits))):
        # the same bits (the usual case): ~0.02 s for a tuning volume, where the NaN-aware
        # comparison below takes 0.14-0.55 s and ran after each of ~50 volume runs of a tune
        return True
    if exact:
        return np.array_equal(a, b, equal_nan=True)
    return bool(np.allclose(a, b, rtol=1e-5, atol=1e-5, equal_nan=True))


def noise(times) -> float:
    """Relative spread of one candidate's repeated timings: (max - min) / min
    (0 for fewer than two)."""
    times = [t for t in times if t is not None]
    if len(times) < 2 or min(times) <= 0:
        return 0.0
    return (max(times) - min(times)) / min(times)


#: A candidate whose first timing is over this many times the rules' best is not
#: timed again (it cannot win by the noise margin; on a GPU the CPU-shaped SGM
#: kernels take 50-200x the rules' and were most of a tune's time)
HOPELESS = 2.0


def _hopeless(times, j) -> bool:
    """Candidate ``j`` (not the rules' own, 0) already timed over HOPELESS x the rules' best."""
    return j > 0 and bool(times[j]) and bool(times[0]) and min(times[j]) > HOPELESS * min(times[0])


def _faster_rounds(rules: dict, cand: dict) -> tuple:
    """``(k, n)``: of the ``n`` rounds in which both the rules' choice and a candidate were
    timed (``{round: seconds}`` each), those in which the candidate was the faster."""
    both = [r for r in cand if r in rules]
    return sum(cand[r] < rules[r] for r in both), len(both)


def _beats(best, rules_best, spread, faster) -> bool:
    """A candidate replaces the rules' choice when its best time beats the rules' best
    by more than their own spread over the rounds (:func:`noise`) while it was the
    faster in most rounds that timed both, or by at least :data:`MARGIN` while it
    was the faster in every round that timed both (at least :data:`PAIRED_ROUNDS`).
    The round-by-round tests compare each candidate run with the rules' run of the
    same round, seconds apart, so a machine whose speed drifts between rounds (a
    shared VM: 12-60 % spreads at 96 rows on a Zen 3) still resolves a clear
    difference, and one lucky best time does not win: on the Zen 3 an SGM width
    16 once beat the rules' 8 by 8.5 % against a spread of 7.2 % while the faster
    in 2 of 5 rounds, and took that SGM from 0.97 to 1.16 s in the pipeline.  A
    tie is the faster in all of 5 rounds one time in 32."""
    k, n = faster
    if best * (1 + spread) < rules_best and (n == 0 or 2 * k > n):
        return True
    return n >= PAIRED_ROUNDS and k == n and best * (1 + MARGIN) < rules_best


#: The least rounds of a paired win (:func:`_beats`)
PAIRED_ROUNDS = 3


def choose(ctx, opts, progress=None, rounds=1) -> tuple:
    """Measure the rules' choice (candidate ``{}``, always first; candidates
    equal to it are dropped) and every other candidate of every option,
    ``rounds`` times interleaved (rules, 1, 2, ..., then the reverse order,
    ...: a change of the machine's load falls on all of them), keeping each
    candidate's best time (one over HOPELESS x the rules' best after a round is
    not timed again).  Another candidate replaces the rules' choice only
    when its best time beats the rules' best by more than the noise (the
    relative spread of the rules' own timings over the rounds,
    :func:`noise`, at least :data:`MARGIN`) while it was the faster in most
    rounds that timed both; or by MARGIN while it was the
    faster in each of at least PAIRED_ROUNDS rounds (:func:`_beats`); of
    several such, the fastest.  A candidate whose output
    differs from the rules' (bit for bit, or to rounding where the option is
    not ``exact``) in any round, or that fails, is never chosen.  Returns
    ``(choices, measured)``: the RULES rows set by the chosen candidates
    (none for an option whose rules' choice stands), and per option each
    candidate's best seconds (None: wrong or failed), the noise and, per
    candidate, ``faster_rounds`` (k, n): faster than the rules in k of the n
    rounds that timed both (None for the rules' own).

    The rules' choice's first run gives the reference output every candidate
    is checked against.  When that run fails (raises), the option cannot be
    checked: it is skipped, with one warning naming the option and the error,
    its rules' choice stands (no candidate is chosen, since none could be
    shown to compute the same result), its ``measured`` entry lists every
    candidate as None and holds the error under ``"error"``, and the other
    options are tuned as usual (the progress callback still counts the
    skipped option's runs).  A failure of the rules' choice in a later, timed
    round, after the reference was taken, leaves the fastest candidate that
    matched the reference."""
    profile = ctx.profile
    choices, measured = {}, {}
    for opt in opts:
        cands = _candidates(profile, opt)
        saved = dict(profile.tuned)
        by_round = [{} for _ in cands]  # round -> seconds, to compare a candidate with the rules' run of its round
        failed = [False] * len(cands)
        try:
            profile.tuned.clear()
            profile.tuned.update(choices)
            try:
                _, reference = opt.run(ctx)
            except Exception as exc:  # noqa: BLE001 - nothing to check the candidates against: skip the option
                log.warning("tuning %s: the rules' own choice failed (%s: %s); option skipped, its rules' "
                            "choice kept", opt.name, type(exc).__name__, exc)
                measured[opt.name] = {"candidates": [[c, None] for c in cands], "noise": MARGIN,
                                      "faster_rounds": [None] * len(cands),
                                      "error": f"{type(exc).__name__}: {exc}"}
                if progress is not None:
                    for _ in range(max(1, int(rounds)) * len(cands)):
                        progress()
                continue
            for r in range(max(1, int(rounds))):
                order = range(len(cands)) if r % 2 == 0 else reversed(range(len(cands)))
                for j in order:
                    if failed[j] or _hopeless([list(t.values()) for t in by_round], j):
                        if progress is not None:
                            progress()
                        continue
                    profile.tuned.clear()
                    profile.tuned.update(choices)
                    _merge(profile.tuned, cands[j])
                    try:
                        sec, output = opt.run(ctx)
                        ok = _same(output, reference, opt.exact)
                    except Exception as exc:  # noqa: BLE001 - a candidate that fails is not chosen
                        log.info("tuning %s: candidate %s failed: %s", opt.name, cands[j], exc)
                        ok = False
                    if ok:
                        by_round[j][r] = sec
                    else:
                        failed[j] = True
                    if progress is not None:
                        progress()
        finally:
            profile.tuned.clear()
            profile.tuned.update(saved)
        best = [None if failed[j] or not by_round[j] else min(by_round[j].values()) for j in range(len(cands))]
        spread = max(MARGIN, noise(list(by_round[0].values())))
        faster = [None] + [_faster_rounds(by_round[0], by_round[j]) for j in range(1, len(cands))]
        measured[opt.name] = {"candidates": [[c, s] for c, s in zip(cands, best)], "noise": spread,
                              "faster_rounds": faster}
        if best[0] is None:  # the rules' own choice failed: the fastest that ran is taken
            good = [(s, j) for j, s in enumerate(best) if s is not None]
            if good:
                _merge(choices, cands[min(good)[1]])
            continue
        beats = [(s, j) for j, s in enumerate(best)
                 if j > 0 and s is not None and _beats(s, best[0], spread, faster[j])]
        if beats:
            _merge(choices, cands[min(beats)[1]])
    return choices, measured


def tune(ctx, progress: bool = False, size=SIZE, rounds=5) -> tuple:
    """Tune ``ctx``'s device, store the choices, apply them to ``ctx.profile``;
    returns ``(choices, measured, path)``."""
    opts = options(ctx, size, repeat=1)
    bar = None
    if progress:
        from tqdm import tqdm

        runs = sum(len(_candidates(ctx.profile, o)) for o in opts)
        bar = tqdm(total=rounds * runs, desc="tuning", unit="run")
    try:
        choices, measured = choose(ctx, opts, None if bar is None else (lambda: bar.update(1)), rounds)
    finally:
        if bar is not None:
            bar.close()
    path = store(ctx.device, choices, measured, size)
    ctx.profile.tuned.clear()
    ctx.profile.tuned.update(choices)
    return choices, measured, path
