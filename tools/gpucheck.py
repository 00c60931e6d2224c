"""The one-call GPU check (``scripts/gpu_check.sh``, which sets up Python and
calls ``python -m tools.gpucheck``): on a machine lent with a GPU, one
run of a few minutes that answers whether the kernels are right there and
how fast the method is, as one markdown report.

Steps, each in a subprocess with its own time limit (a hung kernel costs
its step, not the run; what did not run is named in the report): the OpenCL
platforms and devices; a subset of the kernel-vs-reference tests with
``pytest --cl-device SPEC`` (TEST_GROUPS, most important first, within
TEST_BUDGET_S); ``mccnn-cl bench`` for census on the KITTI-size pair, and
for the networks (the paper architecture's shipped model; fst with random
weights of the published KITTI shape, values do not change the timing),
each with the baselines the bench measures in the same run.  With no GPU
OpenCL device it prints one line naming the likely cause (e.g. NVIDIA's
ICD missing from a CUDA-only image) and exits 0.  ``--cpu`` runs the same
steps on the CPU device (rehearsal; the network benches then at a quarter
of KITTI per side, since a CPU takes minutes for the full size); its time
budgets were set on a 2-core AVX-512 EPYC and scale with the machine's speed
measured at the start (:func:`speed_scale`: numpy's GEMM rate against that
machine's, at most MAX_SCALE times).  Before the tests, ``mccnn-cl tune
--no-binaries`` chooses the kernels on the device (the benches use its
choices; the tests run the rules table, MCCNN_TUNE=off in their conftest).
"""

from __future__ import annotations

import argparse
import glob
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: (title, pytest arguments, modules needed beyond the package's): the
#: kernel-vs-reference tests run on the device, most important first (subsets
#: chosen to take ~200 s on a loaded 2-core CPU, far less on a GPU), selected
#: by marker: ``gpu_check`` where a module's subset is run.
TEST_GROUPS = (
    ("the whole method with a GPU profile against the CPU column; the tuner's GPU candidates",
     ["tests/test_network_gpu.py", "tests/test_cbca_gpu.py", "tests/test_tune.py", "-k",
      "with_the_gpu_profile or gpu_candidates"], ()),
    ("SGM, work-group per line (GPU layout)", ["tests/test_sgm_wg.py", "-m", "gpu_check"], ()),
    ("SGM, CPU-shaped kernels", ["tests/test_sgm.py", "-m", "gpu_check"], ()),
    ("census", ["tests/test_census.py"], ()),
    ("network fst", ["tests/test_fst.py"], ()),
    ("networks, local-memory tiles (GPU layout: conv GEMM, fst volume, fc head)",
     ["tests/test_network_gpu.py", "-m", "gpu_check"], ()),
    ("network acrt", ["tests/test_acrt.py"], ()),
    ("network paper", ["tests/test_network.py", "-m", "gpu_check"], ("torch",)),
    ("cross arms", ["tests/test_cross.py"], ()),
    ("CBCA, work-groups (GPU layout)", ["tests/test_cbca_gpu.py"], ()),
    ("CBCA", ["tests/test_cbca.py", "-m", "gpu_check"], ()),
    ("disparity, interpolation, sub-pixel", ["tests/test_disparity.py"], ()),
    ("refinement filters", ["tests/test_refine.py"], ()),
    ("half-precision volumes", ["tests/test_half.py", "-m", "gpu_check"], ()),
)
#: Seconds: the whole check (set-up excluded), the tests, one test group, one bench
#: (a GPU run must end within a lent machine's 8 minutes, set-up included) ...
TOTAL_BUDGET_S = 440.0
TEST_BUDGET_S = 270.0
GROUP_LIMIT_S = 120.0
BENCH_LIMIT_S = 100.0
#: ... and the ``--cpu`` rehearsal's (under 10 minutes on 2 CPU cores, where a
#: cold kernel cache alone costs minutes of compiling)
CPU_TOTAL_BUDGET_S = 570.0
CPU_TEST_BUDGET_S = 470.0
CPU_GROUP_LIMIT_S = 180.0
#: A group is given at least this long (a scaled-down limit is raised to it) and is not
#: started with less left: on the H200 a group stopped at a scaled 27 s was still building
#: its kernels, which tells nothing
MIN_GROUP_S = 60.0
#: ``mccnn-cl tune`` before the tests (its own limit, within the whole check's)
TUNE_LIMIT_S = 150.0
#: numpy's float32 GEMM rate (GFLOP/s) on the machine the --cpu budgets were set
#: on (2-core AMD EPYC, AVX-512, PoCL pthread-skylake-avx512, idle: ~200,
#: BENCHMARKS.md); a slower or loaded machine gets budgets scaled by the ratio,
#: at most MAX_SCALE times
CPU_REFERENCE_GFLOPS = 200.0
MAX_SCALE = 4.0
#: The shared data files the chosen tests and the bench read (``--pack-data``).
DATA_FILES = ("kitti2015/training/image_2/000000_10.png", "kitti2015/training/image_3/000000_10.png",
              "middlebury/Cones/im0.png", "middlebury/Cones/im1.png")


#: Files that tell a whole shared-data folder (the tests then read it through MCCNN_DATA)
#: from a --pack-data copy (the tests then read their bundled crops, tests/data).
FULL_DATA_FILES = ("middlebury/Tsukuba/im0.png", "kitti2015/training/image_2/000001_10.png")


def tests_env(data, base) -> dict:
    """The tests' environment: MCCNN_DATA names ``data`` when it is a whole shared-data
    folder; beside a --pack-data copy (the benches' files only) or no data the tests
    read their bundled crops (tests/data), so MCCNN_DATA is removed."""
    env = dict(base)
    if data is not None and all((Path(data) / f).is_file() for f in FULL_DATA_FILES):
        env["MCCNN_DATA"] = str(data)
    else:
        env.pop("MCCNN_DATA", None)
    return env


def _run(cmd, limit, env=None):
    """(return code or None when killed at ``limit`` s, output, seconds)."""
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=limit)
        return p.returncode, p.stdout + p.stderr, time.perf_counter() - t0
    except subprocess.TimeoutExpired as exc:
        out = (exc.stdout or b"") + (exc.stderr or b"")
        return None, out.decode(errors="replace") if isinstance(out, bytes) else out, time.perf_counter() - t0


def speed_scale(rate=None) -> tuple:
    """(factor the --cpu budgets are multiplied by, numpy GEMM GFLOP/s measured):
    CPU_REFERENCE_GFLOPS / the rate, between 1 and MAX_SCALE."""
    if rate is None:
        from mccnn_cl.benchmark import numpy_gemm_rate

        rate = numpy_gemm_rate(n=32768, repeat=5)
    gflops = rate / 1e9
    return min(MAX_SCALE, max(1.0, CPU_REFERENCE_GFLOPS / max(gflops, 1e-3))), gflops


def run_tune(spec, limit, env, say):
    """``mccnn-cl tune`` on the device: a row (title, status, seconds, note, output)."""
    # no binaries: the benches time after a warm-up, and the tests build other configurations
    rc, out, sec = _run([sys.executable, "-m", "mccnn_cl", "tune", "--device", spec, "--no-binaries"], limit, env)
    status = "timed out" if rc is None else ("ok" if rc == 0 else f"FAILED (exit {rc})")
    say(f"gpu_check: mccnn-cl tune: {status} ({sec:.0f} s)")
    keep = [ln for ln in out.splitlines() if "tuning:" not in ln]  # the progress bar's redraws
    return ("mccnn-cl tune", status, sec, "", "\n".join(keep).strip())


def devices():
    """[(DeviceInfo, extra facts)] of every OpenCL device; [] when none."""
    from mccnn_cl.opencl.context import list_devices
    from mccnn_cl.errors import NoOpenCLDeviceError

    try:
        devs = list_devices()
    except NoOpenCLDeviceError:
        return []
    out = []
    for d in devs:
        h = d.handle
        facts = (f"{h.max_compute_units} compute units, {h.global_mem_size / 2**30:.1f} GiB, local "
                 f"{h.local_mem_size // 1024} KiB, max work-group {h.max_work_group_size}, "
                 f"driver {h.driver_version.strip()}")
        out.append((d, facts))
    return out


def no_gpu_cause() -> str:
    """The likely reason why no GPU OpenCL device shows up, in one sentence."""
    vendors = sorted(os.path.basename(p) for p in glob.glob("/etc/OpenCL/vendors/*.icd"))
    if os.environ.get("OCL_ICD_VENDORS"):
        vendors.append(f"(OCL_ICD_VENDORS={os.environ['OCL_ICD_VENDORS']})")
    smi = shutil.which("nvidia-smi")
    gpu_named = ""
    if smi:
        rc, out, _ = _run([smi, "-L"], 20)
        gpu_named = out.strip().splitlines()[0] if rc == 0 and out.strip() else ""
    icds = ", ".join(vendors) or "none"
    if gpu_named and not any("nvidia" in v.lower() for v in vendors):
        return (f"nvidia-smi sees '{gpu_named}' but no NVIDIA OpenCL ICD is registered (ICDs: {icds}): a "
                "CUDA-only image; add /etc/OpenCL/vendors/nvidia.icd naming libnvidia-opencl.so.1 (part of "
                "the driver's compute libraries; scripts/gpu_check.sh does this itself when the library exists)")
    if gpu_named:
        return (f"nvidia-smi sees '{gpu_named}' and an NVIDIA ICD is registered (ICDs: {icds}), but the ICD's "
                "library did not load: libnvidia-opencl.so.1 missing or not matching the driver")
    if smi:
        return f"nvidia-smi is installed but lists no GPU (driver not loaded, or no GPU passed in); ICDs: {icds}"
    return f"no GPU driver seen (no nvidia-smi; ICDs registered: {icds})"


def pick(devs, want_cpu: bool, spec=None):
    """(device spec for --cl-device/--device, DeviceInfo) or None."""
    if spec:
        from mccnn_cl.opencl.context import select_device

        handle, _ = select_device(spec)
        hit = next((d for d, _ in devs if d.handle == handle), None)
        return (spec, hit) if hit else None
    kind = "CPU" if want_cpu else "GPU"
    # Oclgrind's simulator reports CPU | GPU: never the GPU under test
    hit = next((d for d, _ in devs if d.type == kind and "oclgrind" not in d.platform.lower()), None)
    if hit is None:
        return None
    return f"{hit.platform_index}:{hit.device_index}", hit


def _pytest_summary(out: str) -> str:
    lines = [ln.strip("= ") for ln in out.splitlines() if re.search(r"\d+ (passed|failed|error)", ln)]
    return lines[-1] if lines else "no summary line"


def run_tests(spec, budget, env, say, group_limit=GROUP_LIMIT_S):
    """Rows (title, status, seconds, summary, failure text) of TEST_GROUPS."""
    rows, t_end = [], time.perf_counter() + budget
    for title, args, needs in TEST_GROUPS:
        left = t_end - time.perf_counter()
        missing = [m for m in needs if importlib.util.find_spec(m) is None]
        floor = min(MIN_GROUP_S, budget)  # a check's whole test budget under the floor: one group gets it
        if missing or left < floor:
            why = f"needs {', '.join(missing)} (not installed)" if missing else "time budget of the tests spent"
            say(f"gpu_check: tests {title}: not run: {why}")
            rows.append((title, "not run", 0.0, why, ""))
            continue
        limit = min(max(group_limit, floor), left)
        cmd = [sys.executable, "-m", "pytest", "-q", "-rfE", "-p", "no:cacheprovider", "--cl-device", spec, *args]
        rc, out, sec = _run(cmd, limit, env)
        if rc is None:
            status, summary = "timed out", f"killed after {limit:.0f} s; last output: " + " | ".join(
                out.strip().splitlines()[-2:])
        else:
            status = "passed" if rc == 0 else f"FAILED (exit {rc})"
            summary = _pytest_summary(out)
        fails = "\n".join(ln for ln in out.splitlines() if ln.startswith(("FAILED", "ERROR"))) if rc else ""
        if rc not in (0, None) and not fails:
            fails = "\n".join(out.strip().splitlines()[-15:])
        say(f"gpu_check: tests {title}: {status}, {summary} ({sec:.0f} s)")
        rows.append((title, status, sec, summary, fails))
    return rows


def _bench_costs():
    """The --cost choices of ``mccnn-cl bench`` (read from its --help)."""
    rc, out, _ = _run([sys.executable, "-m", "mccnn_cl", "bench", "--help"], 60)
    m = re.search(r"--cost \{([^}]*)\}", out)
    return m.group(1).split(",") if m else []


def bench_plan(cpu: bool, data: Path | None, tmp: Path):
    """[(title, bench arguments or None, note)]."""
    from mccnn_cl.models import resolve
    from mccnn_cl.weights import FST, PAPER, Weights, shipped_models

    pair = []
    if data is not None and all((data / f).is_file() for f in DATA_FILES[:2]):
        pair = ["--left", str(data / DATA_FILES[0]), "--right", str(data / DATA_FILES[1])]
    where = "KITTI 2015 000000 (1242 x 375)" if pair else "the synthetic KITTI-size pair"
    costs = _bench_costs()
    plan = [(f"census, {where}", ["--cost", "census", *pair], "")]
    net_pair = ["--size", "240x64", "--max-disp", "128"] if cpu else pair
    net_where = "a 240 x 64 synthetic pair, D = 128 (--cpu: KITTI takes minutes on a CPU)" if cpu else where
    for arch, label in ((PAPER, "paper"), (FST, "fst")):
        if label in costs:  # the bench takes this network by name
            plan.append((f"{label}, {net_where}", ["--cost", label, *net_pair], ""))
            if label == "fst":  # the same bench with the rules' choices: what tuning changed
                plan.append((f"{label}, {net_where}, the rules (MCCNN_TUNE=off)", ["--cost", label, *net_pair],
                             "MCCNN_TUNE=off"))
            continue
        if "cnn" not in costs:
            plan.append((label, None, "not benchmarked: `mccnn-cl bench` has no --cost cnn"))
            continue
        path = next((p for p in shipped_models().values() if resolve(p).architecture == arch), None)
        note = f"shipped model {Path(path).name}" if path else ""
        if path is None:
            try:
                w = Weights.random(conv_layers=[[64, 3]] * 4, architecture=arch, seed=1) if arch == FST else None
            except Exception as exc:  # an architecture this checkout cannot build yet
                w, note = None, f"({type(exc).__name__}: {exc})"
            if w is None:
                plan.append((label, None, f"not benchmarked: no shipped {arch} network {note}".strip()))
                continue
            path = str(tmp / f"random_{label}.npz")
            w.save(path)
            note = "random weights, 4 conv 3x3 layers of 64 maps (the published KITTI fst shape)"
        plan.append((f"{label}, {net_where}", ["--cost", "cnn", "--weights", path, *net_pair], note))
    return plan


def run_benches(spec, plan, repeat, env, say, t_end, limit=BENCH_LIMIT_S):
    rows = []
    for title, args, note in plan:
        left = t_end - time.perf_counter()
        if args is None or left < 15:
            note = note if args is None else "not run: the check's time budget spent"
            say(f"gpu_check: bench {title}: {note}")
            rows.append((title, "skipped", 0.0, note, ""))
            continue
        cmd = [sys.executable, "-m", "mccnn_cl", "bench", "--device", spec, "--repeat", str(repeat), *args]
        run_env = env
        if note == "MCCNN_TUNE=off":
            run_env = dict(os.environ if env is None else env, MCCNN_TUNE="off")
        rc, out, sec = _run(cmd, min(limit, left), run_env)
        status = "timed out" if rc is None else ("ok" if rc == 0 else f"FAILED (exit {rc})")
        say(f"gpu_check: bench {title}: {status} ({sec:.0f} s)")
        rows.append((title, status, sec, note, out.strip()))
    return rows


def report(path, args, spec, target, devs, test_rows, bench_rows, seconds, env_note):
    lines = [f"# GPU check report ({'--cpu rehearsal' if args.cpu else 'GPU'})", "",
             f"- date: {time.strftime('%Y-%m-%d %H:%M:%S %Z')}",
             f"- device under test: `{spec}` = {target}",
             f"- Python: {sys.executable} ({sys.version.split()[0]}); {env_note}",
             f"- whole check: {seconds:.0f} s", "", "## OpenCL platforms and devices", ""]
    lines += [f"- {d.platform_index}:{d.device_index} {d} - {facts}" for d, facts in devs]
    lines += ["", "## Kernel-vs-reference tests (`pytest --cl-device " + spec + "`)", "",
              "| group | status | seconds | summary |", "|---|---|---|---|"]
    lines += [f"| {t} | {s} | {sec:.0f} | {summ} |" for t, s, sec, summ, _ in test_rows]
    for t, s, _, _, fails in test_rows:
        if fails:
            lines += ["", f"### {t}: failures", "", "```", fails[-6000:], "```"]
    lines += ["", "## `mccnn-cl tune`, then `mccnn-cl bench` (with the baselines it measures in the same run)", ""]
    for t, s, sec, note, out in bench_rows:
        lines += [f"### {t}: {s} ({sec:.0f} s)" + (f" - {note}" if note else ""), ""]
        if out:
            lines += ["```", out[-8000:], "```", ""]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def pack_data(src: Path, dst: Path) -> None:
    """Copy DATA_FILES from a shared-data folder to ``dst`` (to carry them to a device machine)."""
    for rel in DATA_FILES:
        (dst / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src / rel, dst / rel)


def find_data(given=None):
    for cand in (given, os.environ.get("MCCNN_DATA"), REPO.parent / "shared" / "data",
                 REPO / "shared" / "data", REPO / ".gpucheck" / "data"):
        if cand and all((Path(cand) / f).is_file() for f in DATA_FILES):
            return Path(cand).resolve()
    return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="gpu_check", description=__doc__.split("\n")[0])
    ap.add_argument("--cpu", action="store_true", help="run the checks on the CPU device (rehearsal)")
    ap.add_argument("--device", help="device spec instead of the first GPU (or CPU with --cpu)")
    ap.add_argument("--out", default="gpu_check_report.md", help="markdown report (default %(default)s)")
    ap.add_argument("--data", help="shared-data folder (default: $MCCNN_DATA, ../shared/data, "
                                   "shared/data, .gpucheck/data)")
    ap.add_argument("--pack-data", metavar="DST", help="only copy the data files the check reads to DST")
    ap.add_argument("--budget", type=float, default=None, metavar="SECONDS",
                    help="the whole check's time budget (set-up excluded); every fixed budget (tune, tests, "
                         "one test group, one bench) shrinks or grows in proportion (default: %.0f s on a GPU, "
                         "%.0f s with --cpu, before the --cpu speed scaling)" % (TOTAL_BUDGET_S, CPU_TOTAL_BUDGET_S))
    ap.add_argument("--tune-seconds", type=float, default=None, metavar="SECONDS",
                    help="the limit of `mccnn-cl tune` (default %.0f s, scaled with --budget)" % TUNE_LIMIT_S)
    ap.add_argument("--env-note", default="", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()

    def say(msg):
        print(msg, flush=True)

    if args.pack_data:
        src = find_data(args.data)
        if src is None:
            say("gpu_check: no shared-data folder with the check's files found (--data DIR)")
            return 2
        pack_data(src, Path(args.pack_data))
        say(f"gpu_check: copied {len(DATA_FILES)} files from {src} to {args.pack_data}")
        return 0
    devs = devices()
    target = pick(devs, args.cpu, args.device)
    if target is None:
        what = "CPU" if args.cpu else "GPU"
        found = "; ".join(str(d) for d, _ in devs) or "no OpenCL device at all"
        say(f"gpu_check: no OpenCL {what} device (found: {found}); likely cause: " +
            (no_gpu_cause() if not args.cpu else "no CPU OpenCL runtime (PoCL: apt install pocl-opencl-icd)"))
        return 0
    spec, info = target
    say(f"gpu_check: OpenCL devices: " + "; ".join(f"{d.platform_index}:{d.device_index} {d}" for d, _ in devs))
    say(f"gpu_check: checking {spec} = {info}")
    data = find_data(args.data)
    if data is None:
        say("gpu_check: no shared data found: the benches on real images are left out (see --pack-data)")
    env = tests_env(data, os.environ)
    test_budget, total_budget, group_limit = ((CPU_TEST_BUDGET_S, CPU_TOTAL_BUDGET_S, CPU_GROUP_LIMIT_S) if args.cpu
                                              else (TEST_BUDGET_S, TOTAL_BUDGET_S, GROUP_LIMIT_S))
    scale, note = 1.0, ""
    if args.budget is not None:
        if not args.budget > 0:
            say(f"gpu_check: --budget must be a positive number of seconds, got {args.budget:g}")
            return 2
        scale = args.budget / total_budget
        note = f"--budget {args.budget:g} s: budgets x {scale:.2f}"
        if not args.cpu:
            say(f"gpu_check: {note}")
    if args.cpu:
        speed, gflops = speed_scale()
        scale *= speed
        note = (note + "; " if note else "") + (
            f"numpy GEMM {gflops:.0f} GFLOP/s against {CPU_REFERENCE_GFLOPS:.0f} on the machine the budgets "
            f"were set on: budgets x {speed:.2f}")
        say(f"gpu_check: speed: {note}")
    tune_limit = args.tune_seconds if args.tune_seconds is not None else TUNE_LIMIT_S * min(scale, MAX_SCALE)
    tune_row = run_tune(spec, tune_limit, env, say)
    test_rows = run_tests(spec, test_budget * scale, env, say, group_limit * scale)
    with tempfile.TemporaryDirectory(prefix="gpu-check-") as tmp:
        bench_rows = run_benches(spec, bench_plan(args.cpu, data, Path(tmp)), 1 if args.cpu else 3, env, say,
                                 t0 + tune_row[2] + total_budget * scale, BENCH_LIMIT_S * scale)
    seconds = time.perf_counter() - t0
    env_note = (args.env_note or "environment as found") + (f"; {note}" if note else "")
    report(args.out, args, spec, info, devs, test_rows, [tune_row] + bench_rows, seconds, env_note)
    bad = [t for t, s, sec, why, _ in test_rows + bench_rows
           if s not in ("passed", "ok", "skipped") and not (s == "not run" and why.startswith("needs"))]
    say(f"gpu_check: report written to {args.out} ({seconds:.0f} s); "
        + (f"not passed: {', '.join(bad)}" if bad else "everything that ran passed"))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
