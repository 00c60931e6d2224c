"""scripts/gpu_check.sh's quick paths (the full check is run by hand on a
machine with a GPU, and with --cpu as a rehearsal: docs/portability.md).

The no-GPU path is forced on any machine by an ICD folder holding only PoCL
(or nothing), so the script's own NVIDIA ICD fix-up is skipped (it never
touches an OCL_ICD_VENDORS that is set): one line on stdout, exit status 0.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO, ImplUnavailable, icd_file

sys.path.insert(0, str(REPO))  # tools/ is outside the installed package
from tools import gpucheck  # noqa: E402

SCRIPT = REPO / "scripts" / "gpu_check.sh"


def _vendors(tmp_path, with_pocl):
    d = tmp_path / "vendors"
    d.mkdir()
    if with_pocl:
        try:
            (d / "pocl.icd").write_text(Path(icd_file("pocl")).read_text())
        except ImplUnavailable as exc:
            pytest.fail(f"PoCL is needed for this test: {exc}")
    return d


def _run_script(tmp_path, vendors, extra_path=None, *args):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OCL_ICD_", "PYOPENCL_CTX"))}
    env["OCL_ICD_VENDORS"] = str(vendors)
    if extra_path:
        env["PATH"] = f"{extra_path}{os.pathsep}{env['PATH']}"
    out = tmp_path / "report.md"
    p = subprocess.run(["bash", str(SCRIPT), "--out", str(out), *args], env=env, capture_output=True, text=True,
                       timeout=120)
    return p, out


@pytest.mark.parametrize("with_pocl", [True, False])
@pytest.mark.slow
def test_no_gpu_prints_one_line_and_exits_0(tmp_path, with_pocl):
    p, out = _run_script(tmp_path, _vendors(tmp_path, with_pocl))
    assert p.returncode == 0, p.stdout + p.stderr
    lines = p.stdout.strip().splitlines()
    assert len(lines) == 1, p.stdout
    assert lines[0].startswith("gpu_check: no OpenCL GPU device") and "likely cause" in lines[0], lines[0]
    assert ("Portable Computing Language" in lines[0]) == with_pocl
    assert not out.exists()  # no tests, no bench, no report


@pytest.mark.slow
def test_no_gpu_names_a_missing_nvidia_icd(tmp_path):
    """nvidia-smi sees a GPU (a stand-in script here) but no OpenCL GPU device
    shows up: the line names the NVIDIA driver / ICD as the cause."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    smi = bin_dir / "nvidia-smi"
    smi.write_text("#!/bin/sh\necho 'GPU 0: NVIDIA H200 (UUID: GPU-0)'\n")
    smi.chmod(0o755)
    p, _ = _run_script(tmp_path, _vendors(tmp_path, True), bin_dir)
    assert p.returncode == 0, p.stdout + p.stderr
    lines = p.stdout.strip().splitlines()
    assert len(lines) == 1 and "nvidia-smi sees 'GPU 0: NVIDIA H200" in lines[0], p.stdout


def test_oclgrind_is_never_the_gpu_under_test():
    """Oclgrind's simulator reports CPU | GPU (listed as a GPU): not picked."""
    from mccnn_cl.opencl.context import DeviceInfo

    sim = DeviceInfo(0, 0, "Oclgrind", "OpenCL 1.2", "Oclgrind Simulator", "GPU", object())
    gpu = DeviceInfo(1, 0, "NVIDIA CUDA", "OpenCL 3.0", "NVIDIA H200", "GPU", object())
    assert gpucheck.pick([(sim, "")], want_cpu=False) is None
    assert gpucheck.pick([(sim, ""), (gpu, "")], want_cpu=False) == ("1:0", gpu)


def test_pack_data_copies_the_files_the_check_reads(tmp_path, shared_data):
    p = subprocess.run([sys.executable, "-m", "tools.gpucheck", "--data", str(shared_data), "--pack-data",
                        str(tmp_path / "data")], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stdout + p.stderr
    for rel in gpucheck.DATA_FILES:
        assert (tmp_path / "data" / rel).read_bytes() == (shared_data / rel).read_bytes()
    assert gpucheck.find_data(tmp_path / "data") == (tmp_path / "data").resolve()


def test_budget_must_be_positive(capsys):
    assert gpucheck.main(["--cpu", "--budget", "0", "--out", "unused.md"]) == 2
    assert "--budget must be a positive number" in capsys.readouterr().out


def test_tests_read_the_bundled_crops_beside_a_packed_copy(tmp_path):
    """A --pack-data copy holds the benches' files only: the tests then get no MCCNN_DATA
    (they read tests/data); a whole shared-data folder is handed to them."""
    packed, full = tmp_path / "packed", tmp_path / "full"
    for root, files in ((packed, gpucheck.DATA_FILES), (full, gpucheck.DATA_FILES + gpucheck.FULL_DATA_FILES)):
        for rel in files:
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_bytes(b"")
    base = {"MCCNN_DATA": "/elsewhere", "PATH": "/bin"}
    assert gpucheck.tests_env(packed, base) == {"PATH": "/bin"}
    assert gpucheck.tests_env(None, base) == {"PATH": "/bin"}
    assert gpucheck.tests_env(full, base) == {"MCCNN_DATA": str(full), "PATH": "/bin"}
    assert base["MCCNN_DATA"] == "/elsewhere"  # the caller's environment is not changed


def test_speed_scale():
    """--cpu budgets scale with the measured speed: 1 at or above the reference
    machine's rate, its ratio below, at most MAX_SCALE."""
    ref = gpucheck.CPU_REFERENCE_GFLOPS * 1e9
    assert gpucheck.speed_scale(ref * 2)[0] == 1.0
    assert gpucheck.speed_scale(ref)[0] == 1.0
    assert abs(gpucheck.speed_scale(ref / 1.5)[0] - 1.5) < 1e-9
    assert gpucheck.speed_scale(ref / 100)[0] == gpucheck.MAX_SCALE
    scale, gflops = gpucheck.speed_scale()
    assert 1.0 <= scale <= gpucheck.MAX_SCALE and gflops > 0


def test_fst_is_benched_with_the_rules_too(tmp_path, monkeypatch):
    """The bench plan times the fst pipeline twice, the second time with MCCNN_TUNE=off
    (the rules' kernels), so a GPU report shows what tuning changed; only that row gets
    the variable."""
    monkeypatch.setattr(gpucheck, "_bench_costs", lambda: ["census", "fst", "cnn"])
    plan = gpucheck.bench_plan(False, None, tmp_path)
    titles = [t for t, _, _ in plan]
    fst = [i for i, t in enumerate(titles) if t.startswith("fst")]
    assert len(fst) == 2 and titles[fst[1]].endswith("the rules (MCCNN_TUNE=off)")
    assert plan[fst[0]][1] == plan[fst[1]][1]
    seen = []

    def fake_run(cmd, limit, env=None):
        seen.append((cmd[-2:], (env or {}).get("MCCNN_TUNE")))
        return 0, "ok", 0.1

    monkeypatch.setattr(gpucheck, "_run", fake_run)
    rows = gpucheck.run_benches("0:0", plan, 1, {"X": "1"}, lambda *_: None, gpucheck.time.perf_counter() + 100)
    assert [s for _, s, _, _, _ in rows].count("ok") == len([p for p in plan if p[1] is not None])
    tunes = [t for _, t in seen]
    assert tunes.count("off") == 1 and tunes[-1] == "off"  # the rules' row is the plan's last
    assert [i for i, (t, _, _) in enumerate(plan) if t.endswith("(MCCNN_TUNE=off)")] == [len(plan) - 1]


def test_a_group_is_given_time_to_build(monkeypatch):
    """A scaled-down group limit is raised to MIN_GROUP_S and no group starts with less
    left than that: a group stopped while building its kernels tells nothing."""
    limits = []

    def fake_run(cmd, limit, env=None):
        limits.append(limit)
        return 0, "1 passed in 1.00s", 25.0  # as if each group had taken 25 s

    monkeypatch.setattr(gpucheck, "_run", fake_run)
    monkeypatch.setattr(gpucheck.time, "perf_counter", lambda: 25.0 * len(limits))  # 25 s a group
    rows = gpucheck.run_tests("0:0", 100.0, None, lambda *_: None, group_limit=27.0)
    assert limits == [gpucheck.MIN_GROUP_S] * 2
    ran = [r for r in rows if r[1] == "passed"]
    assert len(ran) == 2 and all(r[1] == "not run" for r in rows[2:])  # 100 s: at 50 s left, no third group
    limits.clear()
    rows = gpucheck.run_tests("0:0", 30.0, None, lambda *_: None, group_limit=10.0)
    assert limits == [30.0] and rows[0][1] == "passed"  # a budget under the floor: the first group gets it all


def test_nvidia_icd_is_registered_where_a_cuda_image_lacks_it(tmp_path):
    """scripts/nvidia_icd.sh (sourced by gpu_check.sh and gpu_lease.sh): with nvidia-smi on the
    PATH, the driver's OpenCL library present and no NVIDIA ICD registered, `nvidia_icd DIR`
    writes DIR/nvidia.icd naming the library and exports OCL_ICD_VENDORS; with OCL_ICD_VENDORS
    already set, or no library, it changes nothing and returns 1."""
    if any("nvidia" in p.read_text(errors="ignore").lower() for p in Path("/etc/OpenCL/vendors").glob("*.icd")):
        pytest.skip("this machine registers an NVIDIA ICD: the case under test cannot arise")
    bin_dir, lib_dir = tmp_path / "bin", tmp_path / "lib"
    bin_dir.mkdir(), lib_dir.mkdir()
    (bin_dir / "nvidia-smi").write_text("#!/bin/sh\nexit 0\n")
    (bin_dir / "nvidia-smi").chmod(0o755)
    lib = lib_dir / "libnvidia-opencl.so.1"
    lib.write_bytes(b"")
    script = REPO / "scripts" / "nvidia_icd.sh"
    run = ('. "$1"; nvidia_icd "$2"; echo "rc=$? vendors=${OCL_ICD_VENDORS:-} lib=${NVIDIA_ICD_LIB:-}"')
    env = {k: v for k, v in os.environ.items() if k != "OCL_ICD_VENDORS"}
    env.update(PATH=f"{bin_dir}:{env['PATH']}", NVIDIA_ICD_SEARCH=str(lib_dir))

    def sh(dest, **extra):
        out = subprocess.run(["bash", "-c", run, "sh", str(script), str(dest)], env={**env, **extra},
                             capture_output=True, text=True, timeout=60)
        return out.stdout.strip()

    if "libnvidia-opencl" in subprocess.run(["bash", "-c", "ldconfig -p 2>/dev/null"], capture_output=True,
                                            text=True).stdout:
        pytest.skip("ldconfig lists a real NVIDIA OpenCL library here: the search folder is not what is found")
    dest = tmp_path / "vendors"
    assert sh(dest) == f"rc=0 vendors={dest} lib={lib}"
    assert (dest / "nvidia.icd").read_text().strip() == str(lib)
    other = tmp_path / "other"
    assert sh(other, OCL_ICD_VENDORS="/x") == "rc=1 vendors=/x lib="
    assert sh(other, NVIDIA_ICD_SEARCH=str(tmp_path / "none")) == "rc=1 vendors= lib="
    assert not other.exists()
