"""Portability: the OpenCL implementations the suite runs on, and a static
audit of the kernels for what breaks on other implementations.

* Isolation: for each implementation in ``$MCCNN_CL_IMPLS`` (default
  ``pocl,oclgrind,rusticl``: what ``scripts/test.sh`` installs; add ``intel``
  after ``bash scripts/opencl_impls.sh intel``), a subprocess whose
  ``OCL_ICD_VENDORS`` names only that implementation's ``.icd`` sees exactly
  one platform, the expected one, with a device.  A listed implementation
  that is not installed FAILS (with the install hint), never skips.
* Rusticl (and Intel when listed): every stage case of test_oclgrind.py, run
  in a subprocess on that implementation against the numpy references (the
  whole suite on one implementation is ``pytest --cl-impl NAME``, see
  docs/portability.md).
* Static audit of ``kernels/*.cl`` and ``kernels/*.h``: no ``double`` (Rusticl
  on llvmpipe has no fp64), no floating literal without the ``f`` suffix (a
  bare ``0.5`` is a double: fp64 arithmetic where supported, a build error or
  a silent demotion elsewhere), no ``reqd_work_group_size`` (sizes are
  queried on the host), and every kernel file includes ``common.h``.
"""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import CL_IMPLS, REPO, ImplUnavailable, impl_environ

from helpers import BACKGROUND, CASE_KERNELS, STAGE_CASE_TIMEOUT

IMPLS = [s.strip() for s in os.environ.get("MCCNN_CL_IMPLS", "pocl,oclgrind,rusticl").split(",") if s.strip()]
KERNEL_DIR = REPO / "mccnn_cl" / "kernels"
KERNEL_FILES = sorted(KERNEL_DIR.glob("*.cl")) + sorted(KERNEL_DIR.glob("*.h"))

_PROBE = r"""
import json, pyopencl as cl
out = []
for p in cl.get_platforms():
    try:
        devs = p.get_devices()
    except cl.Error:
        devs = []
    out.append({"platform": p.name.strip(), "version": p.version.strip(),
                "devices": [d.name.strip() for d in devs],
                "fp64": ["cl_khr_fp64" in d.extensions for d in devs]})
print(json.dumps(out))
"""


def _env(impl, tmp_path):
    try:
        extra = impl_environ(impl, oclgrind_log=tmp_path / "oclgrind.log")
    except ImplUnavailable as exc:
        pytest.fail(f"OpenCL implementation {impl!r} is listed in MCCNN_CL_IMPLS but unavailable: {exc}")
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("OCLGRIND_", "PYOPENCL_CTX", "RUSTICL_", "OCL_ICD_"))}
    env.update(extra)
    return env


@pytest.mark.parametrize("impl", IMPLS)
def test_one_icd_file_isolates_one_implementation(impl, tmp_path):
    proc = subprocess.run([sys.executable, "-c", _PROBE], env=_env(impl, tmp_path),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    plats = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f"{impl}: {plats}")
    assert len(plats) == 1, f"OCL_ICD_VENDORS should expose only {impl}, got {plats}"
    assert CL_IMPLS[impl]["platform"].lower() in plats[0]["platform"].lower(), plats
    assert plats[0]["devices"], f"{impl} lists no device: {plats}"


def test_unknown_or_missing_implementation_fails_loudly(tmp_path):
    """--cl-impl for an implementation that is not installed is a usage error, not a skip."""
    env = dict(os.environ, VENV=str(tmp_path / "no-venv"), MCCNN_CL_ICD_DIR=str(tmp_path / "icd"))
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "--cl-impl", "intel", str(REPO / "tests" / "test_cl.py")],
                          env=env, capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 4, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "intel-opencl-rt" in proc.stderr, proc.stderr[-2000:]


@pytest.mark.parametrize("case", sorted(CASE_KERNELS))
@pytest.mark.parametrize("impl", [i for i in IMPLS if i in ("rusticl", "intel")])
@pytest.mark.slow
def test_stage_matches_reference_on(impl, case, tmp_path):
    _env(impl, tmp_path)  # fails loudly if unavailable
    # run from the session's start in the background (helpers.BackgroundCases, started by
    # conftest.pytest_collection_finish); the timeout is a guard against hangs, not a speed test:
    # on a slow host (a 2-core Zen 3 whose whole suite took 45 min) the fst case on Rusticl, whose
    # llvmpipe builds the network's kernels, ran past 300 s
    res = BACKGROUND.result(impl, case, timeout=STAGE_CASE_TIMEOUT)
    if res["result"] is None:
        pytest.fail(f"{case} on {impl} crashed (rc {res['returncode']}):\n{res['stderr'][-6000:]}")
    bad = [r for r in res["result"]["checks"] if not r["ok"]]
    assert res["ok"] and not bad, f"{case} on {impl}: kernel != reference: {bad or res['result']}"


# --------------------------------------------------------------------------
# static audit of the kernel sources
# --------------------------------------------------------------------------
# A floating literal without suffix: 1.0, .5, 2., 1e-3, 1.5e3 (not 1.0f, 0x1p3, 2, 1.0h).
_DOUBLE_LITERAL = re.compile(r"(?<![\w.])((?:\d+\.\d*|\.\d+)(?:[eE][-+]?\d+)?|\d+[eE][-+]?\d+)(?![\w.])")


def _code_only(src: str) -> str:
    """The source with comments blanked (line numbers kept) and string literals emptied."""
    src = re.sub(r"/\*.*?\*/", lambda m: re.sub(r"[^\n]", " ", m.group()), src, flags=re.S)
    src = re.sub(r"//[^\n]*", "", src)
    return re.sub(r'"[^"\n]*"', '""', src)


def audit_source(text: str) -> list:
    """Portability findings in one kernel source: ``[(line, message)]``."""
    found = []
    for no, line in enumerate(_code_only(text).splitlines(), 1):
        for m in _DOUBLE_LITERAL.finditer(line):
            found.append((no, f"double literal {m.group()!r} (write {m.group()}f)"))
        if re.search(r"\bdouble\d*\b|cl_khr_fp64", line):
            found.append((no, "double precision (no fp64 on Rusticl/llvmpipe and many GPUs)"))
        if "reqd_work_group_size" in line:
            found.append((no, "reqd_work_group_size: work-group sizes are queried on the host"))
    return found


def test_audit_catches_known_problems():
    src = ("float a = 0.5; float b = 1.0f; /* 2.0 in a comment */\n"
           "double c; float d = 1e-3 * x; float e = .25f + 2.f + 3; // 4.0\n"
           "__attribute__((reqd_work_group_size(64, 1, 1))) __kernel void k() {}\n")
    lines = [no for no, _ in audit_source(src)]
    assert lines == [1, 2, 2, 3], audit_source(src)


def test_kernel_files_exist():
    assert any(f.suffix == ".cl" for f in KERNEL_FILES), f"no kernels in {KERNEL_DIR}"


@pytest.mark.parametrize("path", KERNEL_FILES, ids=lambda p: p.name)
def test_kernel_source_is_portable(path):
    text = path.read_text(encoding="utf-8")
    found = audit_source(text)
    assert not found, "\n".join(f"{path.name}:{no}: {msg}" for no, msg in found)
    if path.suffix == ".cl":
        assert re.search(r'^\s*#\s*include\s+"common\.h"', text, re.M), f"{path.name} does not include common.h"
