"""The tuner (mccnn_cl.opencl.tune): its per-device cache and its choices."""

import dataclasses
import json
import multiprocessing
import os
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from mccnn_cl.atomic import PREFIX, temp_prefix
from mccnn_cl.opencl import tune, tune_cache
from mccnn_cl.opencl.context import ClContext


def fake_device(driver="1.0"):
    return SimpleNamespace(platform=SimpleNamespace(name="Plat", version="OpenCL 3.0 Plat 9"), name="Dev",
                           driver_version=driver)


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("MCCNN_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("MCCNN_TUNE", raising=False)
    monkeypatch.setattr(tune_cache, "_WARNED", set())
    return tmp_path


def test_store_and_load(cache):
    dev = fake_device()
    path = tune.store(dev, {"sgm_cols": 64, "launch_local": [16, 4, 4]}, {})
    assert path.startswith(str(cache)) and os.path.exists(path)
    assert tune.load(dev) == {"sgm_cols": 64, "launch_local": [16, 4, 4]}
    assert [f for f in os.listdir(os.path.dirname(path)) if f.startswith(PREFIX)] == []


def test_off_disables(cache, monkeypatch):
    dev = fake_device()
    tune.store(dev, {"sgm_cols": 64}, {})
    monkeypatch.setenv("MCCNN_TUNE", "off")
    assert tune.load(dev) == {}


def test_corrupt_cache_warns_once_and_is_rewritten(cache):
    dev = fake_device()
    path = tune.store(dev, {"sgm_cols": 64}, {})
    with open(path, "w") as f:
        f.write("{ half a file")
    with pytest.warns(RuntimeWarning, match="ignoring the tuning cache"):
        assert tune.load(dev) == {}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert tune.load(dev) == {}  # one warning per file and process
    tune.store(dev, {"sgm_cols": 32}, {})
    assert tune.load(dev) == {"sgm_cols": 32}


def test_changed_driver_version_is_not_used(cache):
    """A new driver (or package version) keys another file; a file whose
    recorded identity is another device's is ignored with a warning."""
    old, new = fake_device("1.0"), fake_device("2.0")
    tune.store(old, {"sgm_cols": 64}, {})
    assert tune.cache_path(old) != tune.cache_path(new)
    assert tune.load(new) == {}
    os.makedirs(os.path.dirname(tune.cache_path(new)), exist_ok=True)
    os.replace(tune.cache_path(old), tune.cache_path(new))  # a foreign file under the new name
    with pytest.warns(RuntimeWarning, match="another device, driver"):
        assert tune.load(new) == {}


def test_unknown_rows_dropped(cache):
    dev = fake_device()
    tune.store(dev, {"sgm_cols": 64, "no_such_rule": 1}, {})
    assert tune.load(dev) == {"sgm_cols": 64}


def _writer(root, n, value):
    os.environ["MCCNN_CACHE_DIR"] = root
    for i in range(n):
        tune.store(fake_device(), {"sgm_cols": value, "launch_local": [value, i, 1]}, {"pad": "x" * 20000})


def test_two_processes_at_once(cache):
    """Two processes writing the same cache file while a third reads: every
    read sees one whole file (written to a temporary name, then renamed)."""
    ctx_mp = multiprocessing.get_context("spawn")
    procs = [ctx_mp.Process(target=_writer, args=(str(cache), 60, v)) for v in (32, 64)]
    for p in procs:
        p.start()
    seen = set()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a torn file would warn
        while any(p.is_alive() for p in procs):
            got = tune.load(fake_device())
            if got:
                seen.add(got["sgm_cols"])
                assert got["launch_local"][0] == got["sgm_cols"]
    for p in procs:
        p.join()
        assert p.exitcode == 0
    final = json.load(open(tune.cache_path(fake_device())))
    assert final["choices"]["sgm_cols"] in (32, 64)
    assert [f for f in os.listdir(os.path.dirname(tune.cache_path(fake_device()))) if f.startswith(PREFIX)] == []


def test_wrong_candidate_never_chosen(ctx):
    """The fastest candidate gives another output: the slower correct one is chosen;
    a candidate that raises is not chosen either; the rules' choice is measured
    first (a candidate equal to it is not measured twice); the profile is left
    as it was."""
    before = dict(ctx.profile.tuned)
    truth = np.arange(12, dtype=np.float32)
    rules = tune._rules_value(ctx.profile, "sgm_cols")
    times = {64: 0.5, rules: 0.9} if rules != 64 else {48: 0.5, rules: 0.9}
    good = min(times, key=times.get)

    def run(c):
        cols = c.profile.rule("sgm_cols")
        if cols == 16:
            raise RuntimeError("does not build")
        if cols == 32:
            return 0.001, truth + 1  # fastest, wrong
        return times[cols], truth.copy()

    cands = [{"sgm_cols": c} for c in (16, 32, good, rules)]
    choices, measured = tune.choose(ctx, [tune.Option("sgm_cols", cands, run)])
    assert choices == {"sgm_cols": good}
    assert measured["sgm_cols"]["candidates"] == [[{}, 0.9], [cands[0], None], [cands[1], None], [cands[2], 0.5]]
    assert ctx.profile.tuned == before


def test_rules_candidate_kept_unless_faster_than_the_noise(ctx):
    """Another candidate replaces the rules' choice only when faster by more
    than the rules' own spread over the rounds (at least tune.MARGIN) while the
    faster in most rounds, or by MARGIN while the faster in every round: a
    machine whose speed drifts between rounds still resolves a candidate faster
    in each round, and a candidate faster at best but slower in most rounds
    stays out."""
    rules = tune._rules_value(ctx.profile, "sgm_cols")
    other = 32 if rules != 32 else 64
    calls = {"n": 0}
    times = {}  # cols -> function of the round

    def run(c):
        n = calls["n"]  # 0: the rules' reference run; then two runs a round
        calls["n"] += 1
        return times[c.profile.rule("sgm_cols")](max(n - 1, 0) // 2), np.zeros(3)

    opt = tune.Option("sgm_cols", [{"sgm_cols": c} for c in (rules, other)], run)

    def choose(rounds):
        calls["n"] = 0
        return tune.choose(ctx, [opt], rounds=rounds)

    times[rules] = lambda r: 1.0
    times[other] = lambda r: 0.98
    assert choose(3)[0] == {}  # 2 % faster in every round: inside MARGIN
    times[other] = lambda r: 0.5
    assert choose(3)[0] == {"sgm_cols": other}
    # the machine drifts: the rules take 1.0 s in even rounds, 1.3 s in odd ones (30 % spread)
    times[rules] = lambda r: 1.0 if r % 2 == 0 else 1.3
    times[other] = lambda r: 0.8 if r % 2 == 0 else 1.4  # faster at best, slower in odd rounds
    choices, measured = choose(4)
    assert choices == {} and abs(measured["sgm_cols"]["noise"] - 0.3) < 1e-9
    assert measured["sgm_cols"]["faster_rounds"] == [None, (2, 4)]
    times[other] = lambda r: 0.8 * times[rules](r)  # 20 % faster in each round: chosen
    choices, measured = choose(4)
    assert choices == {"sgm_cols": other} and measured["sgm_cols"]["faster_rounds"] == [None, (4, 4)]
    assert choose(2)[0] == {}  # but not on fewer than tune.PAIRED_ROUNDS rounds (0.8 is inside the 30 % spread)
    times[other] = lambda r: 0.65  # beyond the spread
    assert choose(4)[0] == {"sgm_cols": other}
    # one lucky round: 40 % faster than the rules' best in round 0 (beyond their 30 % spread),
    # slower in the other three: not chosen (the Zen 3's SGM width 16, faster in 2 of 5)
    times[other] = lambda r: 0.6 if r == 0 else 1.5
    choices, measured = choose(4)
    assert choices == {} and measured["sgm_cols"]["faster_rounds"] == [None, (1, 4)]
    times[other] = lambda r: 0.6 if r < 3 else 1.5  # faster in 3 of 4 and beyond the spread: chosen
    assert choose(4)[0] == {"sgm_cols": other}
    assert tune.noise([1.0, 1.1, None]) == pytest.approx(0.1) and tune.noise([2.0]) == 0.0


def test_context_applies_stored_choices(cache, ctx, monkeypatch):
    tune.store(ctx.device, {"sgm_cols": 48}, {})
    fresh = ClContext(ctx.device)
    assert fresh.profile.rule("sgm_cols") == 48 and fresh.profile.rule_source("sgm_cols") == "tuned"
    assert fresh.profile.rule_source("cbca_fused") == "rules"
    monkeypatch.setenv("MCCNN_TUNE", "off")
    assert ClContext(ctx.device).profile.rule("sgm_cols") != 48 or tune._rules_value(ctx.profile, "sgm_cols") == 48


@pytest.mark.slow
def test_real_candidates_agree(ctx, cache):
    """Every real option at a small size: the candidates that ran agree with
    the rules (none is wrong here), and the choice is one of them."""
    opts = tune.options(ctx, size=(24, 96, 32), repeat=1)
    choices, measured = tune.choose(ctx, opts)
    for name, res in measured.items():
        results = res["candidates"]
        assert results[0][0] == {} and len(results) > 1, name  # the rules' choice, then the others
        assert all(s is not None for _, s in results), f"{name}: a candidate disagreed with the rules: {results}"
    assert set(choices) <= set().union(*(c for o in opts for c in o.candidates))


@pytest.mark.slow
def test_gpu_candidates_agree(ctx, cache, monkeypatch):
    """A GPU-shaped device's options (a profile built for a GPU, run on this device):
    SGM's and CBCA's work-group paths against the CPU-shaped kernels, the conv GEMM's
    tiles, launch_local; every candidate computes the rules' result, so the tuner on a
    GPU has more than the rules to choose from and nothing wrong among it."""
    import pyopencl as cl

    import helpers
    from mccnn_cl.opencl.device import DeviceProfile

    gpu = helpers.fake_device("Some GPU", cl.device_type.GPU, 8, 1, global_mem=1 << 34, max_alloc=1 << 32,
                              max_work_group=1024)
    monkeypatch.setattr(ctx, "profile", DeviceProfile.of(gpu, cl))
    opts = tune.options(ctx, size=(12, 80, 24), repeat=1)
    assert [o.name for o in opts] == ["sgm", "sgm_wg_cols", "cbca_path", "network_gemm", "launch_local"]
    choices, measured = tune.choose(ctx, opts)
    for name, res in measured.items():
        results = res["candidates"]
        assert results[0][0] == {} and len(results) > 1, name
        assert all(s is not None for _, s in results), f"{name}: a candidate disagreed with the rules: {results}"
    assert set(choices) <= {"sgm_stage", "sgm_paired_max_units", "sgm_cols", "sgm_wg_cols", "cbca_workgroup",
                            "network_gemm_tile", "launch_local"}


def test_devices_lines_name_the_source(cache, ctx):
    from mccnn_cl.cli.tune import describe_choices

    lines = describe_choices(ctx.device)
    assert "not tuned" in lines[0] and all("(rules)" in ln for ln in lines[1:])
    tune.store(ctx.device, {}, {})  # tuned, and the rules' every choice stood
    lines = describe_choices(ctx.device)
    assert "no candidate beat" in lines[0] and all("(rules)" in ln for ln in lines[1:])
    tune.store(ctx.device, {"sgm_cols": 48}, {})
    lines = describe_choices(ctx.device)
    assert "tuned on this device" in lines[0]
    assert any("sgm_cols" in ln and "48" in ln and "(tuned)" in ln for ln in lines)
    assert any("cbca_fused" in ln and "(rules)" in ln for ln in lines)
    if ctx.profile.is_cpu:  # the Winograd block as the stack takes it (XA resolved), or None when tuned off
        rules = dataclasses.replace(ctx.profile, tuned={}).winograd()
        assert any("network_winograd" in ln and str(rules) in ln and "(rules)" in ln for ln in lines)
        tune.store(ctx.device, {"network_winograd": None}, {})
        lines = describe_choices(ctx.device)
        assert any("network_winograd" in ln and "None" in ln and "(tuned)" in ln for ln in lines)


@pytest.mark.slow
def test_tune_command(cache):
    """`mccnn-cl tune` end to end: choices written, then listed by `devices`; the
    default method's kernel binaries stored, so that a new process builds no
    program (its first call would otherwise build those the tuning had measured)."""
    import subprocess
    import sys

    env = dict(os.environ, MCCNN_CACHE_DIR=str(cache), MCCNN_TUNE="on", MCCNN_BINARY_CACHE="on")
    # a small size and 2 rounds: the default KITTI-like size takes ~30-70 s here
    p = subprocess.run([sys.executable, "-m", "mccnn_cl", "tune", "--size", "32x400x64",
                        "--rounds", "2"], env=env, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr
    assert "written to" in p.stdout and "wrong/failed" not in p.stdout
    assert "kernel binaries of the default method stored" in p.stdout
    probe = ("import numpy as np; from mccnn_cl.opencl.context import ClContext; "
             "from mccnn_cl.pipeline import StereoMatcher; ctx = ClContext(None); "
             "rng = np.random.default_rng(1); left = rng.random((40, 320), dtype=np.float32); "
             "[StereoMatcher(cost=c, device=ctx).compute(left, np.roll(left, -2, axis=1)) for c in ('cnn', 'census')]; "
             "print(ctx.builds, ctx.binary_loads)")
    q = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=900)
    assert q.returncode == 0, q.stderr
    builds, loads = map(int, q.stdout.split()[-2:])
    assert builds == 0 and loads > 10, q.stdout
    assert json.load(open(tune.cache_path(ClContext(None).device)))["size"] == [32, 400, 64]
    bad = subprocess.run([sys.executable, "-m", "mccnn_cl", "tune", "--size", "96x1242"], env=env,
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "--size" in bad.stderr
    d = subprocess.run([sys.executable, "-m", "mccnn_cl", "devices"], env=env, capture_output=True, text=True)
    assert "tuned on this device" in d.stdout


def test_wrong_in_any_round_never_chosen(ctx):
    """A candidate right in the first round and wrong in a later one is not chosen."""
    calls = {"n": 0}
    rules = tune._rules_value(ctx.profile, "sgm_cols")
    other = 64 if rules != 64 else 48

    def run(c):
        cols = c.profile.rule("sgm_cols")
        if cols == 32:
            calls["n"] += 1
            return 0.001, np.ones(3) * (calls["n"] >= 2)  # right once, then wrong
        return (0.5 if cols == other else 0.9), np.zeros(3)

    opt = tune.Option("sgm_cols", [{"sgm_cols": 32}, {"sgm_cols": other}], run)
    choices, measured = tune.choose(ctx, [opt], rounds=3)
    assert choices == {"sgm_cols": other} and measured["sgm_cols"]["candidates"][1][1] is None


def test_tile_row_tuned_by_two_options(ctx, cache):
    """Two options tune different sizes of one tile row (network_tiles: the conv's CONV_RM, the
    head's RM): each candidate names only its size, the choices add up, and the profile returns the
    rules' row with the tuned sizes over it (from the cache too)."""
    rules = tune._rules_value(ctx.profile, "network_tiles")
    conv_other, head_other = (6 if rules["CONV_RM"] != 6 else 4), (4 if rules["RM"] != 4 else 8)

    def timed(key, fast):
        def run(c):
            t = c.profile.network_tiles()
            return (0.5 if t[key] == fast else 1.0), np.zeros(3)
        return run

    opts = [tune.Option("conv", [{"network_tiles": {"CONV_RM": v}} for v in (rules["CONV_RM"], conv_other)],
                        timed("CONV_RM", conv_other)),
            tune.Option("head", [{"network_tiles": {"RM": v}} for v in (rules["RM"], head_other)],
                        timed("RM", head_other))]
    assert [len(tune._candidates(ctx.profile, o)) for o in opts] == [2, 2]  # the rules' own value counted once
    choices, _ = tune.choose(ctx, opts)
    assert choices == {"network_tiles": {"CONV_RM": conv_other, "RM": head_other}}
    tune.store(ctx.device, choices, {})
    tiles = ClContext(ctx.device).profile.network_tiles()
    assert tiles == dict(rules, CONV_RM=conv_other, RM=head_other, RN=tiles["RN"])


def test_short_runs_are_timed_several_times(ctx):
    """A run of a few milliseconds is repeated until the round's runs last LEAST_SECONDS (at most
    MAX_RUNS), and the best is kept; a long run is timed `repeat` times."""
    import time as _time
    calls = []

    def short():
        calls.append(1)
        _time.sleep(0.004 if len(calls) != 3 else 0.03)  # one slow run: not the one kept

    best = tune._timed(ctx, short, 1)
    assert 0.004 <= best < 0.02 and 1 + 5 <= len(calls) <= 1 + tune.MAX_RUNS
    calls.clear()
    tune._timed(ctx, lambda: (calls.append(1), _time.sleep(0.12)), 2)
    assert len(calls) == 1 + 2


def test_timed_runs_inside_quiet_the_warm_up_outside(ctx, monkeypatch):
    """The timed runs of a candidate run inside tune.quiet (where `mccnn-cl tune` pauses its
    background build), its warm-up run (which builds) outside it."""
    import contextlib

    log = []

    @contextlib.contextmanager
    def quiet():
        log.append("enter")
        yield
        log.append("exit")

    monkeypatch.setattr(tune, "quiet", quiet)
    tune._timed(ctx, lambda: log.append("run"), 2)
    assert log[0] == "run" and log[1] == "enter" and log[-1] == "exit"
    assert log.count("enter") == 1 and log.count("run") >= 3 and set(log[2:-1]) == {"run"}


def test_background_build_only_for_the_real_runs(cache, monkeypatch):
    """`mccnn-cl tune`'s background build of the default method starts for the real
    BINARY_RUNS only (not when a caller replaced them, nor with MCCNN_TUNE_PREBUILD=off),
    at nice 19; paused() stops and continues it; finish_prebuild(wait=False) ends a paused
    one, finish_prebuild(wait=True) waits for it."""
    import signal
    import subprocess
    import sys
    import time as _time

    from mccnn_cl.cli import tune as cli_tune

    monkeypatch.setattr(cli_tune, "BINARY_RUNS", [("a run", lambda ctx: None)])
    assert cli_tune.start_prebuild(None) is None
    monkeypatch.setattr(cli_tune, "BINARY_RUNS", cli_tune._DEFAULT_RUNS)
    monkeypatch.setenv("MCCNN_TUNE_PREBUILD", "off")
    assert cli_tune.start_prebuild(None) is None
    monkeypatch.delenv("MCCNN_TUNE_PREBUILD")
    # the real helper's command line, with a stand-in program: one that counts while it runs
    counter = cache / "count"
    code = ("import os, sys, time\n"
            "while True:\n"
            "    n = int(open(sys.argv[2]).read() or 0) if os.path.exists(sys.argv[2]) else 0\n"
            "    open(sys.argv[2], 'w').write(str(n + 1)); time.sleep(0.01)\n")
    real_popen = subprocess.Popen

    def popen(argv, **kw):
        assert argv[1] == "-c" and argv[2] == cli_tune._PREBUILD and argv[3] == ""
        return real_popen([sys.executable, "-c", code, "", str(counter)], **kw)

    monkeypatch.setattr(subprocess, "Popen", popen)
    helper = cli_tune.start_prebuild(None)
    assert helper is not None
    try:
        deadline = _time.time() + 60
        while not counter.exists() and _time.time() < deadline:
            _time.sleep(0.05)
        assert os.getpriority(os.PRIO_PROCESS, helper.pid) == 19
        with cli_tune.paused(helper):
            _time.sleep(0.3)  # a write under way when it stopped lands by now
            n = counter.read_text()
            _time.sleep(0.5)
            assert counter.read_text() == n, "a paused helper kept running"
        deadline = _time.time() + 30
        while counter.read_text() == n and _time.time() < deadline:
            _time.sleep(0.05)
        assert counter.read_text() != n, "the helper was not continued"
        with cli_tune.paused(helper):
            cli_tune.finish_prebuild(helper, wait=False)  # SIGKILL: a paused process ends too
        assert helper.returncode == -signal.SIGKILL
    finally:
        if helper.poll() is None:
            helper.kill()
            helper.wait()
    done = real_popen([sys.executable, "-c", "import time; time.sleep(0.5)"])
    cli_tune.finish_prebuild(done, wait=True)
    assert done.returncode == 0
    cli_tune.finish_prebuild(None, wait=True)  # no helper: nothing to do


def test_hopeless_candidates_are_timed_once(ctx):
    """A candidate over tune.HOPELESS x the rules' time in the first round is not timed
    again (it cannot win), while the others are timed every round; the progress count
    still reaches rounds x candidates."""
    rules = tune._rules_value(ctx.profile, "sgm_cols")
    slow, fast = (32, 64) if rules not in (32, 64) else (48, 96)
    times = {rules: 1.0, slow: 50.0, fast: 0.5}
    calls = {c: 0 for c in times}

    def run(c):
        cols = c.profile.rule("sgm_cols")
        calls[cols] += 1
        return times[cols], np.zeros(3)

    ticks = []
    opt = tune.Option("sgm_cols", [{"sgm_cols": slow}, {"sgm_cols": fast}], run)
    choices, measured = tune.choose(ctx, [opt], progress=lambda: ticks.append(1), rounds=4)
    assert choices == {"sgm_cols": fast}
    # the rules: the reference run, then 4 timed rounds; the slow one once; the fast one 4 times
    assert calls == {rules: 5, slow: 1, fast: 4}
    assert measured["sgm_cols"]["candidates"][1] == [{"sgm_cols": slow}, 50.0]
    assert len(ticks) == 4 * 3
    assert not tune._hopeless([[1.0], [1.9]], 1) and tune._hopeless([[1.0], [2.1]], 1)
    assert not tune._hopeless([[1.0], []], 1) and not tune._hopeless([[9.0], [1.0]], 0)


def test_rules_choice_failing_skips_only_its_option(ctx, caplog):
    """The rules' own choice of one option raises (its reference run): that option is
    skipped with one warning naming it and the error, its rules' choice stands (no
    candidate is chosen: nothing to check them against, although the other candidate runs
    and is faster), its candidates are listed as failed with the error, the option after it
    is tuned as usual, the progress count still reaches rounds x candidates and the profile
    is left as it was.  (Before, the exception ended the whole tuning.)"""
    import logging

    before = dict(ctx.profile.tuned)
    rules = tune._rules_value(ctx.profile, "sgm_cols")
    other = 64 if rules != 64 else 48
    chunks = 7 if tune._rules_value(ctx.profile, "wta_chunks") != 7 else 5
    calls = []

    def broken(c):
        cols = c.profile.rule("sgm_cols")
        calls.append(cols)
        if cols == rules:
            raise RuntimeError("rules' kernel does not build")
        return 0.1, np.zeros(3)

    def fine(c):
        return (0.5 if c.profile.rule("wta_chunks") == chunks else 1.0), np.zeros(3)

    opts = [tune.Option("sgm_cols", [{"sgm_cols": other}], broken),
            tune.Option("wta_chunks", [{"wta_chunks": chunks}], fine)]
    ticks = []
    with caplog.at_level(logging.WARNING, logger=tune.log.name):
        choices, measured = tune.choose(ctx, opts, progress=lambda: ticks.append(1), rounds=2)
    assert choices == {"wta_chunks": chunks}  # the second option still tuned; nothing for the first
    assert measured["sgm_cols"]["candidates"] == [[{}, None], [{"sgm_cols": other}, None]]
    assert "does not build" in measured["sgm_cols"]["error"]
    assert calls == [rules]  # no candidate of the skipped option ran
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "sgm_cols" in warned[0].getMessage() \
        and "rules' own choice failed" in warned[0].getMessage() and "does not build" in warned[0].getMessage()
    assert len(ticks) == 2 * 2 + 2 * 2
    assert ctx.profile.tuned == before


# -- the `mccnn-cl tune` command: cache folders, the tuning lock, the binaries' phase ----------

def _fake_tune(calls):
    def fake(ctx, progress=False, size=tune.SIZE, rounds=5):
        calls.append(size)
        return {}, {}, tune.store(ctx.device, {}, {}, size)
    return fake


def test_tune_refuses_an_unwritable_cache_before_measuring(cache, monkeypatch, capsys):
    """A cache folder that cannot be written stops `mccnn-cl tune` before it measures
    (before: minutes of measuring, then a PermissionError), with one line naming the
    folder and how to choose another, status 2.  (A regular file where the folder
    should be: unwritable for root too, unlike a chmod.)"""
    from mccnn_cl.cli import main

    calls = []
    monkeypatch.setattr(tune, "tune", _fake_tune(calls))
    monkeypatch.delenv("MCCNN_BINARY_CACHE", raising=False)
    blocked = cache / "not_a_folder"
    blocked.write_text("x")
    monkeypatch.setenv("MCCNN_CACHE_DIR", str(blocked))
    assert main(["tune", "--no-binaries"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot write the tuning cache folder" in err
    assert os.path.join(str(blocked), "tune") in err and "MCCNN_CACHE_DIR" in err
    monkeypatch.delenv("MCCNN_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocked))
    assert main(["tune", "--no-binaries"]) == 2
    err = capsys.readouterr().err
    assert os.path.join(str(blocked), "mccnn_cl", "tune") in err and "XDG_CACHE_HOME" in err
    # the tuning folder writable, the binaries' not: named, with --no-binaries as the way round
    monkeypatch.delenv("XDG_CACHE_HOME")  # (PoCL keeps its own cache there)
    monkeypatch.setenv("MCCNN_CACHE_DIR", str(cache))
    (cache / "binaries").write_text("x")
    assert main(["tune"]) == 2
    err = capsys.readouterr().err
    assert "cannot write the kernel binary cache folder" in err and str(cache / "binaries") in err
    assert "--no-binaries" in err
    assert calls == []  # nothing measured
    assert main(["tune", "--no-binaries", "--size", "8x64x16"]) == 0 and calls == [(8, 64, 16)]
    assert [f for f in os.listdir(cache / "tune") if f.startswith(PREFIX)] == []  # the probe file deleted


def test_unwritable_cache_says_why_in_the_os_words(cache, monkeypatch):
    """check_cache_writable's reason in parentheses is the OS's (strerror), whether os.makedirs
    failed or atomic.check_writable did (an InputError raised from the OSError of its probe
    file: its own "not writable" is not repeated); an InputError with no cause gives its text."""
    import errno

    from mccnn_cl import atomic
    from mccnn_cl.cli.tune import check_cache_writable
    from mccnn_cl.errors import InputError

    folder = os.path.join(str(cache), "tune")
    (cache / "tune").write_text("x")  # a file where the folder should be: os.makedirs fails
    with pytest.raises(InputError) as exc:
        check_cache_writable(False)
    assert str(exc.value).startswith(f"cannot write the tuning cache folder {folder} (File exists); "
                                     "set MCCNN_CACHE_DIR"), exc.value
    (cache / "tune").unlink()

    def refused(directory):
        raise InputError(f"cannot write into {directory}: not writable") from PermissionError(
            errno.EACCES, "Permission denied")

    def no_cause(directory):
        raise InputError("no probe file")

    for probe, why in ((refused, "Permission denied"), (no_cause, "no probe file")):
        monkeypatch.setattr(atomic, "check_writable", probe)
        with pytest.raises(InputError) as exc:
            check_cache_writable(False)
        assert str(exc.value).startswith(f"cannot write the tuning cache folder {folder} ({why}); "), exc.value


def test_tune_reports_binaries_stored_and_not(cache, monkeypatch, capsys):
    """The binaries' phase says what it does as it goes (a line per step and per binary)
    and how many binaries it stored; when one could not be stored (a disk full here),
    a warning with the count and the error instead of the success line, status 1
    (before: a log warning per binary, then 'kernel binaries ... stored', status 0)."""
    import errno

    from mccnn_cl.cli import main
    from mccnn_cl.cli import tune as cli_tune
    from mccnn_cl.opencl import binaries

    monkeypatch.setattr(tune, "tune", _fake_tune([]))
    monkeypatch.delenv("MCCNN_BINARY_CACHE", raising=False)

    def two_binaries(ctx):
        assert ctx.save_binaries
        binaries.store("ab" + "0" * 62, b"first")
        binaries.store("cd" + "0" * 62, b"second")

    monkeypatch.setattr(cli_tune, "BINARY_RUNS", [("two binaries", two_binaries)])
    assert main(["tune", "--size", "8x64x16"]) == 0
    out = capsys.readouterr().out
    assert "storing kernel binaries 1/1: building the programs of two binaries" in out
    assert "kernel binary 1 stored" in out and "kernel binary 2 stored" in out
    assert f"stored under {cache / 'binaries'}: 2 of 2 stored, 0 already there" in out

    real_write, writes = binaries._write, []

    def disk_full_on_second(tmp, data):
        writes.append(1)
        if len(writes) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_write(tmp, data)

    monkeypatch.setattr(binaries, "_write", disk_full_on_second)
    assert main(["tune", "--size", "8x64x16"]) == 1
    cap = capsys.readouterr()
    assert "kernel binary 1 stored" in cap.out and "kernel binary 2 NOT stored" in cap.out
    assert "stored under" not in cap.out
    assert "warning: only 1 of 2 kernel binaries" in cap.err and "No space left on device" in cap.err
    left = [f for _, _, fs in os.walk(cache / "binaries") for f in fs if f.startswith(PREFIX)]
    assert left == []


def test_store_reports_success(cache, caplog):
    """binaries.store says whether it wrote the file, and tells a recording."""
    from mccnn_cl.opencl import binaries

    seen = []
    with binaries.recording(lambda rec, p, err: seen.append((p, err))) as rec:
        assert binaries.store("ab" + "1" * 62, b"payload") is True
        (cache / "binaries" / "cd").write_text("a file where a folder should be")
        with caplog.at_level("WARNING", logger=binaries.log.name):
            assert binaries.store("cd" + "1" * 62, b"payload") is False
    assert "could not store a kernel binary" in caplog.text
    assert (rec.stored, rec.attempted) == (1, 2) and rec.failed[0][0] == binaries.path("cd" + "1" * 62)
    assert [e is None for _, e in seen] == [True, False]
    assert binaries.store("ab" + "2" * 62, b"payload") is True and rec.attempted == 2  # closed: not counted
    assert binaries.load("ab" + "1" * 62) == b"payload"


def _reader(stream):
    """Lines of a pipe, through a queue (read with a timeout)."""
    import queue
    import threading

    q = queue.Queue()

    def pump():
        for line in stream:
            q.put(line)
        q.put(None)

    threading.Thread(target=pump, daemon=True).start()
    return q


def _wait_for(q, text, timeout=120):
    """The lines read until one holding ``text`` (AssertionError at the end of the stream or the timeout)."""
    import queue
    import time as _time

    seen, end = [], _time.monotonic() + timeout
    while True:
        try:
            line = q.get(timeout=max(0.1, end - _time.monotonic()))
        except queue.Empty:
            raise AssertionError(f"no line with {text!r} within {timeout} s; read: {seen}") from None
        if line is None:
            raise AssertionError(f"the stream ended without a line with {text!r}; read: {seen}")
        seen.append(line)
        if text in line:
            return seen


#: `mccnn-cl tune` in a new process with its measuring replaced by a record of when it ran
#: (FAKE_SECONDS long) and its binaries' phase by two stores with a wait between them
#: (for a line on stdin): what is tested is the command's lock and its output.
_CLI_WITH_FAKES = r'''
import os, sys, time
from mccnn_cl.cli import main
from mccnn_cl.cli import tune as cli_tune
from mccnn_cl.opencl import binaries, tune

def fake_tune(ctx, progress=False, size=tune.SIZE, rounds=5):
    with open(os.environ["FAKE_LOG"], "a") as f:
        f.write(f"start {os.getpid()} {time.time()!r}\n")
    time.sleep(float(os.environ.get("FAKE_SECONDS", "0")))
    path = tune.store(ctx.device, {}, {}, size)
    with open(os.environ["FAKE_LOG"], "a") as f:
        f.write(f"end {os.getpid()} {time.time()!r}\n")
    return {}, {}, path

def blocking_run(ctx):
    binaries.store("ab" + "0" * 62, b"first")
    sys.stdin.readline()
    binaries.store("cd" + "0" * 62, b"second")

tune.tune = fake_tune
cli_tune.BINARY_RUNS = [("a run that waits", blocking_run)]
sys.exit(main(sys.argv[1:]))
'''


def _cli_env(cache, **extra):
    env = dict(os.environ, MCCNN_CACHE_DIR=str(cache), MCCNN_TUNE="on", FAKE_LOG=str(cache / "fake.log"), **extra)
    env.pop("MCCNN_BINARY_CACHE", None)
    return env


def _fake_log(cache):
    if not (cache / "fake.log").exists():
        return []
    return [(w, int(p), float(t)) for w, p, t in (ln.split() for ln in open(cache / "fake.log"))]


def test_tune_waits_for_the_tuning_lock(cache):
    """A `mccnn-cl tune` started while another holds the tuning lock (a process holding
    flock on <cache>/tune/tune.lock) says so and measures only after that one has
    finished; two started together measure one after the other (before: both at once,
    each under the other's load, and the last to write won)."""
    import fcntl
    import subprocess
    import sys
    import time as _time

    (cache / "tune").mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, os, sys; fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT); "
         "fcntl.flock(fd, fcntl.LOCK_EX); os.pwrite(fd, b'pid 4242, since then', 0); print('held', flush=True); "
         "sys.stdin.readline()", str(cache / "tune" / "tune.lock")],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        p = subprocess.Popen([sys.executable, "-c", _CLI_WITH_FAKES, "tune", "--no-binaries", "--size", "8x64x16"],
                             env=_cli_env(cache), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        lines = _wait_for(_reader(p.stdout), "waiting for it to finish")
        assert "pid 4242" in lines[-1] and str(cache / "tune" / "tune.lock") in lines[-1]
        _time.sleep(0.5)
        assert _fake_log(cache) == [] and p.poll() is None  # it waits, measuring nothing
        released = _time.time()
    finally:
        holder.stdin.close()
        holder.wait(timeout=30)
    assert p.wait(timeout=120) == 0, p.stderr.read()
    log = _fake_log(cache)
    assert [w for w, _, _ in log] == ["start", "end"] and log[0][2] >= released
    # the lock is free again (released at exit)
    fd = os.open(cache / "tune" / "tune.lock", os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    finally:
        os.close(fd)

    # two runs started together: one measures, then the other
    (cache / "fake.log").unlink()
    runs = [subprocess.Popen([sys.executable, "-c", _CLI_WITH_FAKES, "tune", "--no-binaries", "--size", "8x64x16"],
                             env=_cli_env(cache, FAKE_SECONDS="2"), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True) for _ in range(2)]
    outs = [r.communicate(timeout=180) for r in runs]
    assert [r.returncode for r in runs] == [0, 0], outs
    log = _fake_log(cache)
    assert [w for w, _, _ in log] == ["start", "end", "start", "end"], log
    assert log[0][1] == log[1][1] and log[2][1] == log[3][1] != log[0][1]
    assert sum("waiting for it to finish" in o for o, _ in outs) <= 1


def test_tune_binaries_progress_reaches_a_pipe(cache):
    """The binaries' phase prints each step and each binary as it happens, flushed, also
    to a pipe (before: nothing for ~34 s, then one line): its first lines are read while
    the process still waits inside the phase."""
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-c", _CLI_WITH_FAKES, "tune", "--size", "8x64x16"], env=_cli_env(cache),
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        q = _reader(p.stdout)
        _wait_for(q, "storing kernel binaries 1/1: building the programs of a run that waits")
        _wait_for(q, "kernel binary 1 stored")
        assert p.poll() is None  # still in the phase: the lines were not held in a buffer until exit
        p.stdin.write("\n")
        p.stdin.flush()
        _wait_for(q, "2 of 2 stored")
    finally:
        if p.poll() is None:
            p.stdin.close()
        p.wait(timeout=120)
    assert p.returncode == 0, p.stderr.read()


def test_stale_temporary_tuning_files_are_deleted(cache):
    """A writer killed (kill -9) between its temporary file and the rename leaves the
    file (mccnn_cl.atomic's pid-named name: they would pile up); the next store
    deletes those of writers no longer running, young or not (before: only those
    over ten minutes old), and keeps one of a running process (a write in progress)."""
    import signal
    import subprocess
    import sys

    killed = ("import os, signal, types; from mccnn_cl.opencl import tune_cache; "
              "os.replace = lambda *a: os.kill(os.getpid(), signal.SIGKILL); "
              "dev = types.SimpleNamespace(platform=types.SimpleNamespace(name='Plat', version='OpenCL 3.0 Plat 9'), "
              "name='Dev', driver_version='1.0'); tune_cache.store(dev, {'sgm_cols': 64}, {})")
    folder = cache / "tune"
    for _ in range(2):
        p = subprocess.Popen([sys.executable, "-c", killed], env=dict(os.environ, MCCNN_CACHE_DIR=str(cache)))
        assert p.wait() == -signal.SIGKILL
        dead = sorted(f for f in os.listdir(folder) if f.startswith(PREFIX))
        assert len(dead) == 1 and dead[0].startswith(temp_prefix(p.pid)) and dead[0].endswith(".json"), dead
        # (the second kill's store deleted the first one's file: they do not pile up)
    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        in_progress = f"{temp_prefix(alive.pid)}in-progress.json"
        (folder / in_progress).write_text("{")
        path = tune.store(fake_device(), {"sgm_cols": 32}, {})
        assert sorted(f for f in os.listdir(folder) if f.startswith(PREFIX)) == [in_progress]
    finally:
        alive.kill()
        alive.wait()
    assert tune.load(fake_device()) == {"sgm_cols": 32} and os.path.dirname(path) == str(folder)


def test_tuning_file_is_written_through_atomic_write(cache, monkeypatch):
    """tune_cache.store writes through mccnn_cl.atomic.atomic_write (the package's one
    way of writing a file whole or not at all)."""
    import mccnn_cl.atomic as atomic

    written, real = [], atomic.atomic_write

    def spy(path, write_fn):
        written.append(os.fspath(path))
        return real(path, write_fn)

    monkeypatch.setattr(atomic, "atomic_write", spy)
    path = tune.store(fake_device(), {"sgm_cols": 32}, {})
    assert written == [path] and tune.load(fake_device()) == {"sgm_cols": 32}


def test_earlier_versions_temporary_tuning_files_are_deleted_when_old(cache):
    """The earlier writer of the tuning file (tempfile.mkstemp(prefix=".tmp-"), before
    mccnn_cl.atomic) left a ``.tmp-*`` file when killed before its rename; nothing deleted
    those any more (before: kept for ever).  A store deletes those of the tuning folder
    unchanged for over ten minutes (that writer's own rule), and keeps a younger one
    (an older version's write in progress, another process or host)."""
    import time

    folder = cache / "tune"
    folder.mkdir()
    old, young = time.time() - 15 * 60, time.time() - 2 * 60
    for name, t in ((".tmp-abc123.json", old), (".tmp-probe-xyz", old), (".tmp-young.json", young)):
        (folder / name).write_text("{")
        os.utime(folder / name, (t, t))
    path = tune.store(fake_device(), {"sgm_cols": 32}, {})
    assert sorted(os.listdir(folder)) == sorted([".tmp-young.json", os.path.basename(path)])
    assert tune.load(fake_device()) == {"sgm_cols": 32}


def test_same_compares_bits_first_then_values():
    """tune._same: equal bits are the same output (the fast comparison); otherwise
    NaNs of another payload still match and a changed value does not, bit for bit
    (exact) or to rounding (not exact); another shape never matches."""
    a = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    a[0, 0, :2] = np.nan
    b = a.copy()
    assert tune._same(a, b, True) and tune._same(a, b, False)
    b.view(np.uint32)[0, 0, 0] |= 1  # another NaN payload
    assert np.isnan(b[0, 0, 0]) and tune._same(a, b, True)
    b[1, 2, 3] = np.nextafter(b[1, 2, 3], np.float32(np.inf))  # one ulp
    assert not tune._same(a, b, True) and tune._same(a, b, False)
    b[1, 2, 3] += 1
    assert not tune._same(a, b, False)
    b = a.copy()
    b[1, 1, 1] = np.nan
    assert not tune._same(a, b, True) and not tune._same(a, b, False)
    assert not tune._same(a, a.reshape(6, 4), True)
    assert tune._same(a.astype(np.float64), a.astype(np.float64), True)
