"""``mccnn-cl tune``: kernel choices by measurement (:mod:`mccnn_cl.opencl.tune`), then
the kernel binaries of the default method stored (:mod:`mccnn_cl.opencl.binaries`).

Before measuring it checks that the cache folders can be written (a read-only
cache would otherwise fail after minutes of measuring) and takes the tuning
lock (:func:`mccnn_cl.opencl.tune_cache.tuning_lock`: a second run waits for the
first instead of measuring under its load); the lock is held until the binaries
are stored.  The binaries' phase prints a line per step and per binary, and
reports how many were stored; when some could not be, a warning and status 1."""

from __future__ import annotations

import contextlib
import os
import sys
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
    names = ("sgm_paired_max_units", "sgm_cols", "sgm_width", "cbca_fused", "cbca_multi", "network_winograd",
             "fst_volume_width", "wta_chunks", "mirror_lines", "sgm_mirror_reads", "launch_local")
    if not profile.is_cpu:  # the GPU-shaped paths and the GEMM tile are tuned there
        names = ("sgm_stage", "sgm_cols", "sgm_wg_cols", "cbca_workgroup", "launch_local", "network_gemm_tile")
    for name in names:
        value = profile.value(name)
        note = ", 3 x 3 conv layers' (RT, XA) or None (direct)" if name == "network_winograd" else ""
        lines.append(f"  {name:22s} {value!s:14s} ({profile.rule_source(name)}){note}")
    if not profile.is_cpu:
        return lines
    tiles, mine = profile.network_tiles(), profile.tuned.get("network_tiles", {})
    for key, what in (("CONV_RM", "conv pixels per work-item"), ("CONV_RN", "fst conv channels per work-item"),
                      ("RM", "head cells per work-item")):
        label = f"network_tiles {key}"
        lines.append(f"  {label:22s} {tiles[key]!s:14s} ({'tuned' if key in mine else 'rules'}), {what}")
    return lines


def _say(text: str) -> None:
    print(text, flush=True)  # flushed: progress reaches a pipe or a log file as it happens


def _cache_hint() -> str:
    if os.environ.get("MCCNN_CACHE_DIR"):
        return "set MCCNN_CACHE_DIR (now " + repr(os.environ["MCCNN_CACHE_DIR"]) + ") to a writable folder"
    return "set MCCNN_CACHE_DIR (or XDG_CACHE_HOME) to choose a writable cache folder"


def check_cache_writable(binaries_too: bool) -> None:
    """InputError naming the folder when the tuning cache (or, ``binaries_too``, the
    binary cache) cannot be written: found before minutes of measuring, not after."""
    from ..atomic import check_writable
    from ..errors import InputError
    from ..opencl import binaries, tune_cache

    folders = [("tuning cache", tune_cache.folder(), "")]
    if binaries_too:
        folders.append(("kernel binary cache", os.path.join(binaries.cache_root(), "binaries"),
                        ", or pass --no-binaries"))
    for what, folder, alt in folders:
        try:
            os.makedirs(folder, exist_ok=True)
            check_writable(folder)  # a file created for real (os.access says yes to root on a read-only mount)
        except (OSError, InputError) as exc:
            raise InputError(f"cannot write the {what} folder {folder} ({_why(exc)}); {_cache_hint()}{alt}") from exc


def _why(exc) -> str:
    """Why a cache folder cannot be written, in the OS's words: the OSError's ``strerror``
    (``exc`` itself, from ``os.makedirs``, or the one check_writable's InputError was raised
    from), else the exception's text."""
    from ..errors import InputError

    if isinstance(exc, InputError) and exc.__cause__ is not None:
        exc = exc.__cause__
    return getattr(exc, "strerror", None) or str(exc)


def _sample_pair():
    import numpy as np

    rng = np.random.default_rng(0)
    left = rng.random((40, 320), dtype=np.float32)
    return left, np.roll(left, -3, axis=1)


def _default_method(cost):
    def run(ctx):
        from ..pipeline import StereoMatcher

        StereoMatcher(cost=cost, device=ctx).compute(*_sample_pair())
    return run


#: What the binaries' phase runs, (label, function of a context): a small pair of
#: each cost of the default method, so that the kernels built lazily are stored too.
BINARY_RUNS = [("the fst network's method (cost cnn)", _default_method("cnn")),
               ("the census method", _default_method("census"))]
_DEFAULT_RUNS = BINARY_RUNS

#: The helper process's code: the binaries' phase, its output discarded.
_PREBUILD = "import sys\nfrom mccnn_cl.cli.tune import store_binaries\nsys.exit(store_binaries(sys.argv[1] or None))"


def _low_priority() -> None:  # pragma: no cover - runs in the child between fork and exec
    os.nice(19)
    try:  # Linux: the helper ends with the tuning process, however that ends
        import ctypes
        import signal

        ctypes.CDLL(None).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG (SIGKILL: also when paused)
    except (OSError, AttributeError):
        pass


def start_prebuild(device):
    """The binaries' phase started in a second process at the lowest priority
    (``nice`` 19), or None (``MCCNN_TUNE_PREBUILD=off``, no ``os.nice``, or
    :data:`BINARY_RUNS` replaced).  Why: building and fetching the default
    method's programs takes ~20 s on 2 cores when PoCL's cache is cold (PoCL
    builds one program at a time per process), and the tuning leaves a core
    idle while it compiles its candidates; the helper takes that core and
    hardly any time while the tuner measures (it gets ~1.5 % of a core
    against a process at nice 0), and it is paused (SIGSTOP, SIGCONT) while
    a candidate's runs are timed (:data:`mccnn_cl.opencl.tune.quiet`).  It
    stores the binaries of the choices in force when it starts (the rules, or
    an earlier tuning's); the phase run after the tuning then finds those of
    unchanged programs already there."""
    import subprocess

    if os.environ.get("MCCNN_TUNE_PREBUILD", "on").lower() in ("off", "0", "no") or \
            BINARY_RUNS is not _DEFAULT_RUNS or not hasattr(os, "nice"):
        return None
    try:
        return subprocess.Popen([sys.executable, "-c", _PREBUILD, "" if device is None else str(device)],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                preexec_fn=_low_priority)
    except OSError:
        return None


def _signal(helper, sig) -> None:
    try:
        os.kill(helper.pid, sig)
    except ProcessLookupError:  # it ended meanwhile
        pass


@contextlib.contextmanager
def paused(helper):
    """The helper stopped (SIGSTOP) inside the block, continued after it."""
    import signal

    running = helper.poll() is None
    if running:
        _signal(helper, signal.SIGSTOP)
    try:
        yield
    finally:
        if running:
            _signal(helper, signal.SIGCONT)


def finish_prebuild(helper, wait: bool) -> None:
    """Wait for the helper (``wait``; at most 10 minutes), else end it (SIGKILL:
    a paused one too; a binary it was writing stays a temporary file, which a
    later store deletes)."""
    import subprocess

    if helper is None or helper.poll() is not None:
        return
    if wait:
        _say("waiting for the background build of the default method's programs")
        try:
            helper.wait(timeout=600)
            return
        except subprocess.TimeoutExpired:
            pass
    helper.kill()
    helper.wait()


def store_binaries(device) -> int:
    """Run :data:`BINARY_RUNS` on a new context that saves the programs it builds;
    print each step and each binary stored; 0 when every one was stored, else 1."""
    from ..opencl import binaries
    from ..opencl.context import ClContext

    t1 = time.perf_counter()
    root = os.path.join(binaries.cache_root(), "binaries")
    # a new context: the tuning's context already holds the programs it measured,
    # which would be reused unsaved (and it chose its tiles before the choices existed)
    bctx = ClContext(device)
    bctx.save_binaries = True

    def noted(rec, path, error):
        state = "stored" if error is None else f"NOT stored ({error})"
        _say(f"  kernel binary {rec.attempted} {state} ({time.perf_counter() - t1:.0f} s)")

    with binaries.recording(noted) as rec:
        for i, (label, fn) in enumerate(BINARY_RUNS, 1):
            _say(f"storing kernel binaries {i}/{len(BINARY_RUNS)}: building the programs of {label}")
            fn(bctx)
    there = bctx.binary_loads
    took = f"({time.perf_counter() - t1:.0f} s)"
    if not rec.failed:
        _say(f"kernel binaries of the default method stored under {root}: {rec.stored} of {rec.attempted} "
             f"stored, {there} already there {took}")
        return 0
    path, error = rec.failed[0]
    print(f"mccnn-cl: warning: only {rec.stored} of {rec.attempted} kernel binaries of the default method "
          f"stored under {root} ({type(error).__name__}: {error}); the programs without one are built from "
          f"source in later processes (the tuned choices were written) {took}", file=sys.stderr, flush=True)
    return 1


def run(args) -> int:
    from ..opencl import tune, tune_cache

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
    from ..opencl import binaries

    with_binaries = not args.no_binaries and binaries.enabled()
    check_cache_writable(with_binaries)

    def waiting(holder):
        _say(f"another `mccnn-cl tune` holds {tune_cache.lock_path()} ({holder or 'holder unknown'}): waiting "
             "for it to finish, so that the two do not measure under each other's load (Ctrl-C to stop)")

    with tune_cache.tuning_lock(waiting):
        helper = start_prebuild(args.device) if with_binaries else None
        quiet = tune.quiet
        if helper is not None:
            tune.quiet = lambda: paused(helper)
        try:
            return _tune_and_store(args, size, rounds, with_binaries, helper)
        finally:
            tune.quiet = quiet
            finish_prebuild(helper, wait=False)  # ended when the tuning failed or was interrupted


def _tune_and_store(args, size, rounds, with_binaries, helper) -> int:
    """The measuring and, with ``with_binaries``, the binaries' phase (after the helper)."""
    from ..opencl import tune
    from ..opencl.context import ClContext

    ctx = ClContext(args.device)
    _say(f"tuning {ctx.describe()} at {'x'.join(map(str, size))} (rows x columns x levels), {rounds} rounds")
    t0 = time.perf_counter()
    choices, measured, path = tune.tune(ctx, progress=True, size=size, rounds=rounds)
    for name, res in measured.items():
        parts = []
        for (cand, sec), won in zip(res["candidates"], res["faster_rounds"]):
            label = " ".join(f"{k}={v}" for k, v in cand.items()) or "rules"
            text = "wrong/failed" if sec is None else f"{sec * 1e3:.1f} ms"
            if sec is not None and won and won[1]:
                text += f" (faster in {won[0]}/{won[1]})"
            parts.append(f"{label}: {text}")
        print(f"  {name} (noise {res['noise']:.0%}): " + "; ".join(parts))
    _say(f"choices {choices or 'none (the rules table stands)'}\nwritten to {path} "
         f"({time.perf_counter() - t0:.0f} s)")
    if with_binaries:
        finish_prebuild(helper, wait=True)
        return store_binaries(args.device)
    return 0
