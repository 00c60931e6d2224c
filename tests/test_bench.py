"""mccnn_cl.benchmark: the one stage-grouping table, the synthetic pair, and the
baselines and floors of ``mccnn-cl bench`` (their arithmetic, with fake timings:
timing values themselves are not testable on a shared machine)."""

import importlib.util
import json
import os
import types
from pathlib import Path

import numpy as np
import pytest

from mccnn_cl import benchmark
from mccnn_cl.benchmark import GROUPS, STAGE_GROUP, group_timings, stage_group, synthetic_pair
from mccnn_cl.hyperparameters import Hyperparameters
from mccnn_cl.settings import authors_settings
from mccnn_cl.pipeline import StereoMatcher


@pytest.mark.parametrize("kw", [{}, {"right_reference": "derived"}, {"memory_limit": 2 << 20, "tile_overlap": 8}])
def test_every_timed_stage_has_a_group(ctx, kw):
    left, right = synthetic_pair(120, 90, 16)
    res = StereoMatcher(cost="census", max_disparity=16, device=ctx, **kw).compute(left, right, timings=True)
    assert res.plan.tiled == ("memory_limit" in kw)
    missing = sorted(set(res.timings) - set(STAGE_GROUP))
    assert not missing, f"add these stage names to mccnn_cl.benchmark.STAGE_GROUP: {missing}"
    groups = group_timings(res.timings)
    assert list(groups) == list(GROUPS)
    assert sum(groups.values()) == pytest.approx(sum(res.timings.values()))
    assert groups["CBCA"] > 0 and groups["SGM"] > 0 and groups["cost"] > 0


def test_groups():
    assert [stage_group(n) for n in ("C_CNN", "C_CNN_upload", "cross_R", "C_R_SGM", "right_volume", "D_BF")] == \
        ["cost", "cost", "CBCA", "SGM", "rest", "rest"]
    assert [stage_group(n) for n in ("census_extra", "my_cbca", "sgm2", "whatever")] == ["cost", "CBCA", "SGM", "rest"]
    assert set(STAGE_GROUP.values()) <= set(GROUPS)


def test_synthetic_pair_shifts_by_the_slanted_field():
    left, right = synthetic_pair(80, 40, 20, seed=1)
    assert left.shape == right.shape == (40, 80) and left.dtype == right.dtype == np.uint8
    assert left.std() > 20
    # row 0's disparity is 0.15 (D - 1) = 2.85: right(x) ~ left(x + d) away from the borders
    d = 0.15 * 19
    x = np.arange(10, 60)
    interp = np.interp(x + d, np.arange(80), left[0].astype(np.float64))
    assert np.abs(interp - right[0, 10:60].astype(np.float64)).mean() < 4


# -- baselines and floors: the arithmetic, with fake timings ---------------------------------------

class FakeClock:
    """A perf_counter that moves only when told (stands for ``time`` in mccnn_cl.benchmark)."""

    def __init__(self):
        self.t = 100.0

    def perf_counter(self):
        return self.t


def test_numpy_gemm_rate_times_a_kept_output_after_a_warm_up(monkeypatch):
    clock, outs = FakeClock(), []
    durations = [50.0, 2.0, 0.5, 3.0]  # the warm-up's (excluded), then three timed runs

    def fake_matmul(a, b, out=None):
        assert out is not None and out.shape == (a.shape[0], b.shape[1]) and out.dtype == np.float32
        assert a.dtype == b.dtype == np.float32
        outs.append(out)
        clock.t += durations.pop(0)
        return out

    monkeypatch.setattr(benchmark, "time", types.SimpleNamespace(perf_counter=clock.perf_counter))
    monkeypatch.setattr(np, "matmul", fake_matmul)
    rate = benchmark.numpy_gemm_rate(n=64, k=8, repeat=3)
    assert not durations  # warm-up + 3 runs, every product through np.matmul(..., out=)
    assert all(o is outs[0] for o in outs)  # one output array kept: no fresh allocation timed
    assert rate == pytest.approx(2.0 * 64 * 8 * 8 / 0.5)  # best of the timed runs; the warm-up left out


class _Event:
    def __init__(self, ns):
        self.profile = types.SimpleNamespace(start=5_000, end=5_000 + ns)

    def wait(self):
        pass


class _FakeCL:
    """Just enough of pyopencl for copy_baseline: copies on a profiling queue
    report the durations given (ns); the context's own queue refuses them."""

    class Error(Exception):
        pass

    command_queue_properties = types.SimpleNamespace(PROFILING_ENABLE=2)
    device_type = types.SimpleNamespace(CPU=2, GPU=4)

    def __init__(self, durations_ns, profiling=True, clock=None):
        self.durations, self.profiling, self.clock, self.copies = list(durations_ns), profiling, clock, []

    def CommandQueue(self, context, properties=0):
        if properties and not self.profiling:
            raise self.Error("no profiling here")
        return _Queue(properties)

    def enqueue_copy(self, queue, dst, src, byte_count):
        self.copies.append((queue.properties, byte_count))
        if queue.properties:
            return _Event(self.durations.pop(0))
        sec = self.durations.pop(0) * 1e-9
        if self.clock is not None:
            self.clock.t += sec  # the fallback: wall time passes as the copy runs
        return None


class _Queue:
    def __init__(self, properties):
        self.properties = properties

    def finish(self):
        pass


class _Buf:
    def release(self):
        pass


class _FakeCtx:
    max_alloc = 1 << 40

    def __init__(self, cl, cpu=True):
        self.cl, self.context, self.queue = cl, object(), _Queue(0)
        self.profile = types.SimpleNamespace(is_cpu=cpu)

    def empty(self, nbytes, what=""):
        return _Buf()

    def fill(self, buf, value, nbytes):
        pass

    def finish(self):
        """ctx.finish polls with sleeps: a timer through it would measure the wait loop."""
        self.cl.finish_calls = getattr(self.cl, "finish_calls", 0) + 1


def test_copy_baseline_reads_profiling_events_not_the_wait_loop(monkeypatch):
    # warm-up 90 ms (left out), then 40, 30, 50 ms by the device's clock; the host's clock
    # never moves, so a time taken around ctx.finish() (the polling wait) reads 0
    clock = FakeClock()
    monkeypatch.setattr(benchmark, "time", types.SimpleNamespace(perf_counter=clock.perf_counter))
    cl = _FakeCL([90e6, 40e6, 30e6, 50e6])
    rate = benchmark.copy_bandwidth(_FakeCtx(cl))
    assert rate == pytest.approx(2 * (256 << 20) / 0.030)  # best of 3, read + write counted
    assert [props for props, _ in cl.copies] == [2] * 4  # all on the profiling queue
    base = benchmark.copy_baseline(_FakeCtx(_FakeCL([90e6, 40e6, 30e6, 50e6])), repeat=3)
    assert base["nbytes"] == 256 << 20 and base["timer"] == "OpenCL profiling events"
    assert base["seconds"] == pytest.approx(0.030) and base["rate"] == pytest.approx(rate)


def test_device_seconds_without_profiling_times_copies_back_to_back(monkeypatch):
    clock = FakeClock()
    monkeypatch.setattr(benchmark, "time", types.SimpleNamespace(perf_counter=clock.perf_counter))
    # no profiling queue: warm-up (1 copy), then 2 rounds of 4 copies with one wait each
    cl = _FakeCL([1e9] + [10e6] * 4 + [20e6] * 4, profiling=False, clock=clock)
    ctx = _FakeCtx(cl)
    sec, timer = benchmark.device_seconds(
        ctx, lambda q: cl.enqueue_copy(q, None, None, byte_count=8), repeat=2, back_to_back=4)
    assert sec == pytest.approx(0.010) and "back to back" in timer
    assert len(cl.copies) == 9 and all(props == 0 for props, _ in cl.copies)


def test_copy_baseline_on_the_device(ctx):
    base = benchmark.copy_baseline(ctx, repeat=2, nbytes=8 << 20)
    assert base["nbytes"] == 8 << 20 and base["seconds"] > 0 and base["repeat"] == 2
    assert base["rate"] == pytest.approx(2 * base["nbytes"] / base["seconds"])
    assert base["timer"] in ("OpenCL profiling events", "8 back to back, one blocking wait")


class _FakeCost:
    def __init__(self, flop):
        self.flop = flop

    def flops(self, h, w, d):
        return {"total": self.flop}


def _matcher(cost_name="cnn", settings=None, flop=0.0, vdtype="float32", cpu=True, D=100, margin=4):
    return types.SimpleNamespace(cost_name=cost_name, params=Hyperparameters(**(settings or {})),
                                 cost=_FakeCost(flop), max_disparity=D, margin=margin, vdtype=np.dtype(vdtype),
                                 ctx=_FakeCtx(_FakeCL([]), cpu=cpu))


SHAPE = (58, 108)  # 50 x 100 cells inside a margin of 4
V = 100 * 50 * 100 * 4  # D x h x w float32
GEMM, COPY = 200e9, 20e9


def test_volume_bytes_float16_is_half():
    assert benchmark.volume_bytes(_matcher(), SHAPE) == V
    assert benchmark.volume_bytes(_matcher(vdtype="float16"), SHAPE) == V // 2
    assert benchmark.volume_bytes(_matcher(), SHAPE, max_disparity=10) == V // 10


def test_floor_fst_kitti():
    """fst with the authors' KITTI settings (no CBCA): FLOP at the GEMM rate + SGM 2 V per reference
    (aggregated right reference: 4 V) + the rest (right volume 2 V, WTA 2 V) at the copy rate."""
    m = _matcher(settings=authors_settings("mccnn-fst", "kitti"), flop=2.148e11)
    f = benchmark.floors(m, SHAPE, V, COPY, GEMM)
    assert f == pytest.approx({"cost": 2.148e11 / GEMM, "CBCA": 0.0, "SGM": 4 * V / COPY, "rest": 4 * V / COPY})
    assert sum(f.values()) == pytest.approx(2.148e11 / GEMM + 8 * V / COPY)


def test_floor_paper_network():
    """The paper's settings (4 CBCA iterations before and after SGM, aggregated right reference):
    CBCA 3 rounds x 2 V, SGM 4 V, rest 4 V, plus FLOP / GEMM."""
    m = _matcher(flop=5.12e13)
    f = benchmark.floors(m, SHAPE, V, COPY, GEMM)
    assert f == pytest.approx({"cost": 5.12e13 / GEMM, "CBCA": 6 * V / COPY, "SGM": 4 * V / COPY,
                               "rest": 4 * V / COPY})


def test_floor_census_has_no_network_term():
    m = _matcher(cost_name="census", flop=1e30)
    f = benchmark.floors(m, SHAPE, V, COPY, GEMM)
    assert "cost" not in f and sum(f.values()) == pytest.approx(14 * V / COPY)


def test_floor_sgm_two_volumes_per_reference_and_float16_halves():
    derived = _matcher(cost_name="census", settings={"right_reference": "derived"})
    t = benchmark.stage_traffic(derived.params, V)
    assert t == {"CBCA": 4 * V, "SGM": 2 * V, "rest": 2 * V}  # 2 rounds, one reference, WTA only
    assert benchmark.stage_traffic(_matcher().params, V)["SGM"] == 4 * V
    half = _matcher(cost_name="census", vdtype="float16")
    v16 = benchmark.volume_bytes(half, SHAPE)
    assert sum(benchmark.floors(half, SHAPE, v16, COPY).values()) == pytest.approx(7 * V / COPY)


def test_traffic_floor_convention():
    # one read of V counts V bytes against a copy rate that counts read + write
    assert benchmark.traffic_floor(V, COPY) == pytest.approx(V / COPY)


GROUPS_T = {"cost": 0.5, "CBCA": 0.06, "SGM": 0.04, "rest": 0.05}


def test_rate_table_uses_the_given_baselines(monkeypatch):
    def no(*a, **k):
        raise AssertionError("baselines given: nothing to measure")
    monkeypatch.setattr(benchmark, "numpy_gemm_rate", no)
    monkeypatch.setattr(benchmark, "copy_bandwidth", no)
    lines = []
    m = _matcher(flop=5e10)
    r = benchmark.rate_table(m, SHAPE, GROUPS_T, 0.7, 0.1, V, lines.append, copy_bw=COPY, gemm=GEMM)
    floor = 5e10 / GEMM + 14 * V / COPY
    assert r["pipeline_floor"] == pytest.approx(floor) and r["pipeline_ratio"] == pytest.approx(0.7 / floor)
    assert r["ratios"]["cost"] == pytest.approx(0.5 / (5e10 / GEMM))
    assert r["ratios"]["SGM"] == pytest.approx(0.04 / (4 * V / COPY))
    text = "\n".join(lines)
    net = next(line for line in lines if line.startswith("matching cost"))
    assert "host CPU numpy GEMM 200.0 GFLOP/s" in net and net.endswith(f"{0.5 / (5e10 / GEMM):.2f}x")
    assert f"floor {floor:.3f} s" in text


def test_rate_table_gives_a_gpu_network_no_host_gemm_floor(monkeypatch):
    monkeypatch.setattr(benchmark, "numpy_gemm_rate", lambda *a, **k: pytest.fail("host GEMM measured for a GPU"))
    lines = []
    m = _matcher(flop=5e10, cpu=False)
    r = benchmark.rate_table(m, SHAPE, GROUPS_T, 0.7, 0.1, V, lines.append, copy_bw=COPY, gemm=GEMM)
    assert r["gemm"] is None and r["gemm_on_device"] is False and r["pipeline_floor"] is None
    assert "cost" not in r["ratios"] and r["ratios"]["SGM"] == pytest.approx(0.04 / (4 * V / COPY))
    net = next(line for line in lines if line.startswith("matching cost"))
    assert "host CPU" in net and net.rstrip().endswith("-")
    assert any("runs on the host CPU, not on this device" in line for line in lines)


def test_compare_baselines_takes_the_better_and_warns():
    copy = lambda rate: {"rate": rate, "nbytes": 256 << 20, "timer": "OpenCL profiling events", "repeat": 3}
    before, after = {"copy": copy(10e9), "gemm": 100e9}, {"copy": copy(12e9), "gemm": 110e9}
    chosen, lines = benchmark.compare_baselines(before, after, (1.0, 1.5), 2)
    assert chosen["copy"] == 12e9 and chosen["copy_from"] == "after"
    assert chosen["gemm"] == 110e9 and chosen["gemm_from"] == "after"
    text = "\n".join(lines)
    assert "best of 3" in text and "host CPU" in text and "100.0 / 110.0 GFLOP/s" in text
    assert "10.00 / 12.00 GB/s" in text
    # copy moved 20 % (> 15 %): one warning; GEMM moved 10 %: none; load under the cores: none
    assert len(chosen["warnings"]) == 1 and "copy baseline moved 20%" in chosen["warnings"][0]
    chosen, _ = benchmark.compare_baselines({"copy": copy(10e9), "gemm": None}, {"copy": copy(10.5e9), "gemm": None},
                                            (3.5, 1.0), 2)
    assert chosen["gemm"] is None and chosen["copy_from"] == "after"
    assert len(chosen["warnings"]) == 1 and "above the 2 cores (at the start 3.50)" in chosen["warnings"][0]


def test_bench_command_float16_volume_and_baselines(ctx, monkeypatch, capsys):
    """``mccnn-cl bench --volume-dtype float16``: the volume (printed and in the floors) at 2 bytes a
    cell; baselines measured before and after the timed runs, the better one used; load printed."""
    from mccnn_cl.cli import bench as cli_bench, commands, main

    made = commands._make_matcher
    monkeypatch.setattr(commands, "_make_matcher", lambda args, d, w, **kw: made(args, d, w, ctx=ctx, **kw))
    calls = []

    def fake_baselines(c, gemm=True, repeat=3):
        calls.append(gemm)
        rate = 10e9 if len(calls) == 1 else 11e9
        return {"copy": {"rate": rate, "nbytes": 1 << 20, "timer": "fake", "repeat": 3}, "gemm": None}

    monkeypatch.setattr(cli_bench, "measure_baselines", fake_baselines, raising=False)
    seen = {}
    real_table = cli_bench.rate_table

    def table(matcher, shape, groups, total, sgbm_time, vol, say=print, **kw):
        seen.update(vol=vol, **kw)
        return real_table(matcher, shape, groups, total, sgbm_time, vol, say, **kw)

    monkeypatch.setattr(cli_bench, "rate_table", table)
    rc = main(["bench", "--cost", "census", "--size", "120x60", "--max-disp", "16", "--volume-dtype", "float16"])
    out = capsys.readouterr().out
    assert rc == 0, out
    h, w = 60 - 8, 120 - 8
    assert seen["vol"] == 16 * h * w * 2
    assert f"cost volume: 16 x {h} x {w} float16" in out
    assert calls == [False, False]  # census: no GEMM; before and after the timed runs
    assert seen["copy_bw"] == 11e9 and "using 11.00 (after)" in out
    assert "load average (1 min)" in out and f"{os.cpu_count()} cores" in out and "at the end" in out
    assert "best of 1" in out


# -- tools/benchmarks scripts: their arithmetic and plumbing ---------------------------------------

SCRIPTS = Path(__file__).resolve().parents[1] / "tools" / "benchmarks"


def _script(name, monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPTS))  # bench_fst imports bench_network
    spec = importlib.util.spec_from_file_location(f"_bench_script_{name}", SCRIPTS / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_script_docstrings_name_tools_benchmarks():
    stale = [f"{p.name}: {line.strip()}" for p in sorted(SCRIPTS.glob("*.py"))
             for line in p.read_text().splitlines()
             if "python bench/" in line or "-m bench." in line or " bench/bench_" in line]
    assert not stale, stale


def test_scripts_find_the_shared_data_one_way(monkeypatch, tmp_path):
    """Every script finds the shared data through _paths.data_dir: $MCCNN_DATA, else
    ../shared/data beside the repository (no script with its own variable or path)."""
    own = [p.name for p in sorted(SCRIPTS.glob("*.py")) if p.name != "_paths.py"
           and ('"shared"' in p.read_text() or "MCCNN_SHARED_DATA" in p.read_text()
                or 'environ.get("MCCNN_DATA"' in p.read_text())]
    assert not own, own
    paths = _script("_paths", monkeypatch)
    monkeypatch.setenv("MCCNN_DATA", str(tmp_path))
    assert paths.data_dir() == tmp_path and paths.data_dir("x") == Path("x")
    monkeypatch.delenv("MCCNN_DATA")
    assert paths.data_dir() == paths.REPO.parent / "shared" / "data"
    assert (paths.REPO / "tools" / "benchmarks" / "_paths.py").is_file()


def test_confidence_floor_is_one_read_at_the_copy_rate(monkeypatch):
    mod = _script("bench_confidence", monkeypatch)
    # bench's convention: copy_bw counts read + write, a read of V bytes moves V
    assert mod.read_floor(V, COPY) == pytest.approx(V / COPY)


def test_fst_volume_floors_one_convention(monkeypatch):
    mod = _script("bench_fst", monkeypatch)
    nbytes = 400e6
    r = mod.volume_vs_floors(nbytes, t_vol=0.060, t_copy=0.040, t_fill=0.030)
    assert r["copy_rate"] == pytest.approx(2 * nbytes / 0.040)  # read + write, as bench
    assert r["floor_fill"] == pytest.approx(0.030) and r["ratio_fill"] == pytest.approx(2.0)
    assert r["floor_copy"] == pytest.approx(0.020) and r["ratio_copy"] == pytest.approx(3.0)
    assert r["vol_rate"] == pytest.approx(nbytes / 0.060) and r["fill_rate"] == pytest.approx(nbytes / 0.030)


def test_fst_gemm_shapes_named_and_outputs_kept(monkeypatch):
    mod = _script("bench_fst", monkeypatch)
    conv = [(np.zeros((64, cin, 3, 3), np.float32), None) for cin in (1, 64, 64, 64)]
    w = types.SimpleNamespace(conv=conv)
    shapes = mod.gemm_shapes(w, 20, 30)
    assert shapes == [(18 * 28, 9, 64), (16 * 26, 576, 64), (14 * 24, 576, 64), (12 * 22, 576, 64)]
    assert mod.shapes_text([(5, 9, 64), (4, 576, 64), (4, 576, 64)]) == "(5 x 9) @ (9 x 64), (4 x 576) @ (576 x 64) x2"
    outs = []
    real = np.matmul

    def spy(a, b, out=None):
        outs.append(out)
        return real(a, b, out=out)

    monkeypatch.setattr(np, "matmul", spy)
    run, flop, got = mod.gemm_job(w, 20, 30, 1)
    assert got == shapes and flop == 2 * sum(2 * m * k * n for m, k, n in shapes)
    run()
    assert len(outs) == 2 * 2 * 4 and all(o is not None for o in outs)  # warm-up + a run, both images
    assert outs[:4] == outs[4:8]  # the same kept outputs every time


def test_aggregation_sgm_traffic_follows_the_kernels(monkeypatch):
    mod = _script("bench_aggregation", monkeypatch)
    assert mod.sgm_traffic(types.SimpleNamespace(paired=True), V) == 5 * V
    assert mod.sgm_traffic(types.SimpleNamespace(paired=False), V) == 11 * V


def test_dask_bench_reads_mccnn_data(monkeypatch, tmp_path):
    monkeypatch.setenv("MCCNN_DATA", str(tmp_path))
    assert _script("bench_dask", monkeypatch).SHARED == tmp_path / "kitti2015" / "training"
    monkeypatch.delenv("MCCNN_DATA")
    repo = SCRIPTS.parents[1]
    assert _script("bench_dask", monkeypatch).SHARED == repo.parent / "shared" / "data" / "kitti2015" / "training"


AGG_OUT = """device: X; 2 CPUs, load average 1.0
volume: D x H x W = 32 x 94 x 310, 4 MB
buffer copy           0.5 ms  12.00 GB/s (read + write of one volume), cpu 1 ms
cross arms (x2)       1.0 ms, cpu 2 ms
CBCA 4 it (max_arm=  3, multi    )      4.0 ms   2.00 GB/s (1.0 ms per iteration), cpu 8 ms
CBCA 4 it (max_arm=  3, fused    )     10.0 ms   2.00 GB/s (2.5 ms per iteration), cpu 20 ms
CBCA 4 it (max_arm=255, running  )     70.0 ms   2.00 GB/s (17.5 ms per iteration), cpu 140 ms
CBCA 4 it (max_arm=  3, workgroup)     88.0 ms   2.00 GB/s (22.0 ms per iteration), cpu 170 ms
SGM 4 directions      3.0 ms   6.00 GB/s (paired kernels, 5 V), cpu 6 ms
"""


def test_run_runtimes_reads_padded_cbca_kinds(monkeypatch):
    rows = _script("run_runtimes", monkeypatch).parse_aggregation(AGG_OUT)
    assert rows == pytest.approx({"buffer copy": 0.0005, "cross arms (x2)": 0.001,
                                  "CBCA 4 it (max_arm=3, multi)": 0.004, "CBCA 4 it (max_arm=3, fused)": 0.010,
                                  "CBCA 4 it (max_arm=255, running)": 0.070,
                                  "CBCA 4 it (max_arm=3, workgroup)": 0.088, "SGM 4 directions": 0.003})


def _bench_out(cost):
    gemm = ("  host CPU numpy float32 GEMM (131072 x 300) @ (300 x 300): 80.0 / 90.0 GFLOP/s, using 90.0 (after)\n"
            if cost == "cnn" else "")
    return (f"device: fake (Portable Computing Language)\n"
            f"host: 2 cores, load average (1 min) 1.00 at the start\n"
            f"total ({cost} pipeline)          0.500\n"
            f"host: 2 cores, load average (1 min) 1.00 at the start, 3.50 at the end\n"
            f"baselines before / after the timed runs (each the best of 3; the floors use the better):\n"
            f"{gemm}"
            f"  device buffer copy of 256 MiB (read + write counted; OpenCL profiling events): 20.00 / 21.00 GB/s, "
            f"using 21.00 (after)\n"
            f"warning: load average (1 min) above the 2 cores (at the end 3.50): other work shared the machine\n")


def test_run_runtimes_passes_weights_and_keeps_baselines(monkeypatch, tmp_path):
    mod = _script("run_runtimes", monkeypatch)
    cmds = []

    def fake_run(cmd, env, impl):
        cmds.append(cmd)
        if "bench_aggregation.py" in cmd[1]:
            return AGG_OUT, "fake"
        return _bench_out(cmd[cmd.index("--cost") + 1]), "fake"

    monkeypatch.setattr(mod, "impl_env", lambda impl: dict(os.environ))
    monkeypatch.setattr(mod, "run", fake_run)
    out = tmp_path / "r.json"
    mod.main(["--quick", "--impls", "pocl", "--weights", "kitti-paper", "--json", str(out)])
    benches = [c for c in cmds if "bench" in c and "-m" in c]
    assert len(benches) == 3  # census (steady state), network D = 1 (untimed), network timed
    for c in benches:
        cost = c[c.index("--cost") + 1]
        assert (c[c.index("--weights") + 1] == "kitti-paper") if cost == "cnn" else "--weights" not in c, c
    r = json.loads(out.read_text())
    assert r["weights"] == "kitti-paper"
    b = r["baselines"]["pocl"]
    assert b["host CPU numpy GEMM (GFLOP/s)"] == [80.0, 90.0]
    assert b["device buffer copy (GB/s, read + write)"] == [20.0, 21.0]
    assert b["load average (1 min)"] == [1.0, 3.5] and b["cores"] == 2 and len(b["warnings"]) == 1
    assert "aggregation: CBCA 4 it (max_arm=3, multi)" in r["seconds"]["pocl"]
    # without --weights: bench's default, nothing passed
    cmds.clear()
    mod.main(["--quick", "--impls", "pocl"])
    assert not any("--weights" in c for c in cmds)


def test_sgm_int16_prototype_matches_its_integer_reference(ctx, monkeypatch, capsys):
    """tools/benchmarks/sgm_int16.py --check: the short-lane prototype whose timings BENCHMARKS.md
    reports computes the paired sweeps' recurrence (exact integers), with 16-bit and float volumes."""
    mod = _script("sgm_int16", monkeypatch)
    assert mod.check(ctx) == 0
    assert capsys.readouterr().out.count("the same integers as the reference") == 3


def test_sgm_int16_reference_sees_a_wrong_penalty(monkeypatch):
    """The prototype's reference is not blind: another P1 changes its integers."""
    mod = _script("sgm_int16", monkeypatch)
    rng = np.random.default_rng(3)
    c = rng.integers(0, 1024, (32, 4, 32)).astype(np.int16)
    bigs = mod.flag_table(rng, 32, np.int16)
    a = mod.reference(c, bigs, 2)
    b = mod.reference(c, bigs, 2, pen=(21,) + mod.PEN_SHORT[1:])
    assert a.shape == c.shape and not np.array_equal(a, b)
