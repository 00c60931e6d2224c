"""Shared pytest fixtures.

``--cl-device SPEC`` (or ``$MCCNN_CL_DEVICE``) chooses the OpenCL device for
the whole run (see :func:`mccnn_cl.opencl.context.select_device`); default: the package's
own preference.  A missing OpenCL platform is a test *failure*, never a skip.

``--cl-impl {pocl,intel,oclgrind,rusticl}`` (or ``$MCCNN_CL_IMPL``) runs the
whole pytest *process* on one OpenCL implementation: :func:`pytest_configure`
points the ICD loader at that implementation's single ``.icd`` file
(``OCL_ICD_VENDORS``, written by ``scripts/opencl_impls.sh``) and sets the
implementation's own environment, before pyopencl first asks for platforms
(the loader reads ``OCL_ICD_VENDORS`` once, at first use).  The ``ctx``
fixture then checks that its platform really is that implementation.  An
implementation that is requested but not installed stops the run with an
install hint (usage error, exit status 4), never a skip.  Known gaps of one
implementation are expected failures for that implementation only: mark a
test ``@pytest.mark.cl_impl_xfail("rusticl", reason=...)`` or list its node id
in :data:`KNOWN_GAPS`.  See docs/portability.md.

Real data: the ``shared_data`` fixture is ``$MCCNN_DATA`` when set (a full
data folder: CI sets ``../shared/data``), else ``tests/data``, small crops
bundled with the tests in their datasets' official layouts
(tests/data/README.md).  A test that needs more than those crops (whole
images, other scenes, dataset counts) is marked ``@pytest.mark.full_data``:
without ``$MCCNN_DATA`` it is skipped with that reason (``-rs`` lists it).
"""


import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from mccnn_cl.opencl.context import ClContext

# The suite checks the rules table's choices: a tuning cache of the machine
# (mccnn-cl tune) is not applied unless a run asks for it (MCCNN_TUNE=on).
os.environ.setdefault("MCCNN_TUNE", "off")

REPO = Path(__file__).resolve().parents[1]
#: the real crops bundled with the tests (tests/data/README.md)
BUNDLED_DATA = REPO / "tests" / "data"
FULL_DATA_REASON = "needs the full data set: set MCCNN_DATA to a data folder (CI: ../shared/data)"

# Value written into output buffers before a launch: no kernel ever writes it
# (it is neither a cost, a disparity nor the NaN marking invalid cells), so an
# element left unwritten makes the comparison fail.
POISON = np.float32(-1.2345e30)
POISON_F16 = np.float16(-65504.0)  # half volumes' poison: the most negative finite half

# One entry per OpenCL implementation the suite knows how to isolate:
# ``platform`` is a substring of its CL_PLATFORM_NAME.  The environment each
# needs (OCL_ICD_VENDORS and its own variables, e.g. RUSTICL_ENABLE=llvmpipe,
# OCLGRIND_DATA_RACES=1 ...) comes from ``scripts/opencl_impls.sh --env``.
CL_IMPLS = {
    "pocl": {"platform": "Portable Computing Language"},
    # PoCL made to build AVX2 code (POCL_KERNELLIB_NAME=avx2): the code a Zen 3
    # or Haswell-class CPU runs, on whatever x86-64 machine has AVX2
    "pocl-avx2": {"platform": "Portable Computing Language", "device": "haswell"},
    "intel": {"platform": "Intel(R) OpenCL"},
    # Oclgrind never aborts: it logs to OCLGRIND_LOG (set per run, see
    # impl_environ) and a test fails when that log grows.
    "oclgrind": {"platform": "Oclgrind"},
    # Mesa's Rusticl on llvmpipe (no cl_khr_fp64).
    "rusticl": {"platform": "rusticl"},
}

# Known gaps, as {impl: {node id (relative to the repository): reason}}: such a
# test is xfail on that impl only, strict (an unexpected pass is reported)
# unless the reason is given as (reason, False) for gaps that depend on speed.
KNOWN_GAPS: dict = {
    "intel": {},
    "rusticl": {
        # measured: the network kernels run ~460x slower on llvmpipe than on PoCL
        # (docs/portability.md), so the shipped-network demo cannot finish in the
        # test's 180 s; its results agree with PoCL where it does finish
        "tests/test_cli.py::test_demo_with_shipped_weights":
            ("the full-size network on the demo pair needs far more than the test's 180 s "
             "subprocess timeout on Rusticl/llvmpipe", False),
        "tests/test_bench_scaling.py::test_quick_run_json_is_consistent":
            ("the quick scaling run includes network timings, which take longer than the "
             "test's 120 s subprocess timeout on Rusticl/llvmpipe", False),
    },
    "oclgrind": {
        # measured: Oclgrind simulates the queued kernels inside clFlush, on the thread that
        # flushes (ctx.wait's main thread), so a signal is handled only once they are done
        # (23 s after SIGINT in the test); PoCL, Intel's runtime and Rusticl run them on threads
        # of their own
        "tests/test_cl.py::test_ctrl_c_interrupts_a_wait":
            "Oclgrind runs the queued kernels inside clFlush on the flushing (main) thread",
    },
    "pocl": {},
    "pocl-avx2": {},
}

# Oclgrind's API checker reports one clGetDeviceInfo(CL_INVALID_VALUE) when
# pyopencl probes an OpenCL 2.x/3.x device parameter while building a program
# on this 1.2 device: pyopencl's own probe, not ours, so it is ignored.
OCLGRIND_BENIGN = ("Function: clGetDeviceInfo", "Error:    CL_INVALID_VALUE", "For argument 'param_name'")


class ImplUnavailable(RuntimeError):
    """A requested OpenCL implementation is not installed (message has the install hint)."""


def _impls_script(impl: str, *flags) -> str:
    if impl not in CL_IMPLS:
        raise ImplUnavailable(f"unknown OpenCL implementation {impl!r}; known: {', '.join(CL_IMPLS)}")
    proc = subprocess.run(["bash", str(REPO / "scripts" / "opencl_impls.sh"), "--no-install", *flags, impl],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise ImplUnavailable(proc.stderr.strip() or f"opencl_impls.sh {impl} failed ({proc.returncode})")
    return proc.stdout


def icd_file(impl: str) -> str:
    """Path of the single-implementation ``.icd`` file for ``impl`` (written, never installed).

    Runs ``scripts/opencl_impls.sh --no-install impl``; raises
    :class:`ImplUnavailable` with the script's install hint when missing.
    """
    return _impls_script(impl).strip().splitlines()[-1]


def impl_environ(impl: str, oclgrind_log=None) -> dict:
    """Environment variables that make a *new* process use only ``impl``
    (``scripts/opencl_impls.sh --env``).

    ``oclgrind_log``: file for ``OCLGRIND_LOG`` (oclgrind only; required there).
    """
    env = dict(line.split("=", 1) for line in _impls_script(impl, "--env").splitlines() if "=" in line)
    if impl == "oclgrind":
        if oclgrind_log is None:
            raise ValueError("oclgrind needs a log file (OCLGRIND_LOG)")
        env["OCLGRIND_LOG"] = str(oclgrind_log)
    return env


def oclgrind_errors(text: str) -> str:
    """Oclgrind messages in ``text`` (log or stderr) minus the benign pyopencl probe."""
    blocks, cur = [], []
    for line in text.splitlines():
        if not line.strip():
            if cur:
                blocks.append(cur)
            cur = []
        else:
            cur.append(line)
    if cur:
        blocks.append(cur)
    keep = []
    for b in blocks:
        body = "\n".join(b)
        if all(s in body for s in OCLGRIND_BENIGN):
            continue
        keep.append(body)
    return "\n\n".join(keep)


def pytest_addoption(parser):
    parser.addoption("--cl-device", default=os.environ.get("MCCNN_CL_DEVICE"),
                     help="OpenCL device spec for the tests (see mccnn_cl.opencl.context.select_device)")
    parser.addoption("--cl-impl", default=os.environ.get("MCCNN_CL_IMPL") or None,
                     choices=sorted(CL_IMPLS),
                     help="run this pytest process on one OpenCL implementation only "
                          "(sets OCL_ICD_VENDORS; see docs/portability.md)")


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "cl_impl_xfail(impl, reason): known gap of one OpenCL implementation "
        "(xfail under --cl-impl impl only)")
    impl = config.getoption("--cl-impl")
    if not impl:
        return
    try:
        env = impl_environ(impl, oclgrind_log=Path(tempfile.mkdtemp(prefix="mccnn-oclgrind-")) / "oclgrind.log")
    except ImplUnavailable as exc:
        raise pytest.UsageError(f"--cl-impl {impl}: {exc}") from None
    os.environ.update(env)
    config._mccnn_cl_impl_env = env


def pytest_collection_finish(session):
    """Start the selected stage cases on other implementations in the background
    (tests/helpers.py, BackgroundCases): they build for minutes on one core
    while the rest of the suite runs."""
    pairs = []
    for item in session.items:
        if getattr(item, "originalname", None) != "test_stage_matches_reference_on":
            continue
        if item.get_closest_marker("skip") or item.get_closest_marker("xfail"):
            continue
        params = item.callspec.params
        pairs.append((params["impl"], params["case"]))
    if pairs and not session.config.getoption("collectonly"):
        from helpers import BACKGROUND, STAGE_CASE_TIMEOUT

        BACKGROUND.start(pairs, timeout=STAGE_CASE_TIMEOUT)


def pytest_unconfigure(config):
    helpers = sys.modules.get("helpers")
    if helpers is not None:
        helpers.BACKGROUND.stop()


def pytest_report_header(config):
    impl = config.getoption("--cl-impl")
    if impl:
        return f"OpenCL implementation: {impl} (OCL_ICD_VENDORS={os.environ.get('OCL_ICD_VENDORS')})"
    return None


def full_data_root():
    """``$MCCNN_DATA`` as a Path, None when unset; set but missing is an error."""
    value = os.environ.get("MCCNN_DATA")
    if not value:
        return None
    p = Path(value).resolve()
    if not p.is_dir():
        raise pytest.UsageError(f"MCCNN_DATA={value}: no such folder")
    return p


def pytest_collection_modifyitems(config, items):
    if full_data_root() is None:
        skip = pytest.mark.skip(reason=FULL_DATA_REASON)
        for item in items:
            if item.get_closest_marker("full_data"):
                item.add_marker(skip)
    impl = config.getoption("--cl-impl")
    if not impl:
        return
    gaps = KNOWN_GAPS.get(impl, {})
    for item in items:
        reason, strict = gaps.get(item.nodeid), True
        if isinstance(reason, tuple):
            reason, strict = reason
        for m in item.iter_markers("cl_impl_xfail"):
            if m.args and m.args[0] == impl:
                reason = m.kwargs.get("reason", f"known gap of {impl}")
                strict = m.kwargs.get("strict", True)
        if reason:
            item.add_marker(pytest.mark.xfail(reason=f"[{impl}] {reason}", strict=strict))


@pytest.fixture(scope="session")
def ctx(request):
    """One ClContext for the whole session."""
    c = ClContext(request.config.getoption("--cl-device"))
    print(f"\nOpenCL device under test: {c.describe()}")
    impl = request.config.getoption("--cl-impl")
    if impl:
        want = CL_IMPLS[impl]["platform"]
        got = c.device.platform.name.strip()
        if want.lower() not in got.lower():
            pytest.fail(f"--cl-impl {impl}: the context runs on platform {got!r}, not {want!r} "
                        f"(was pyopencl used before pytest_configure? OCL_ICD_VENDORS="
                        f"{os.environ.get('OCL_ICD_VENDORS')})")
        dev = CL_IMPLS[impl].get("device")
        if dev and dev not in c.device.name.lower():
            pytest.fail(f"--cl-impl {impl}: the device is {c.device.name!r}, whose name lacks {dev!r} "
                        f"(the implementation's variables: {_impls_script(impl, '--env').split()})")
    yield c
    c.close()


@pytest.fixture(autouse=True)
def _oclgrind_log_guard(request):
    """Under ``--cl-impl oclgrind``: a test fails if the Oclgrind log grew during it."""
    if request.config.getoption("--cl-impl") != "oclgrind":
        yield
        return
    log = Path(os.environ["OCLGRIND_LOG"])
    start = log.stat().st_size if log.exists() else 0
    yield
    if log.exists() and log.stat().st_size > start:
        with open(log, encoding="utf-8", errors="replace") as f:
            f.seek(start)
            errors = oclgrind_errors(f.read())
        if errors:
            pytest.fail("Oclgrind reported errors during this test:\n" + errors[:20000], pytrace=False)


@pytest.fixture(scope="session")
def shared_data():
    """The real data: ``$MCCNN_DATA`` when set, else the bundled crops (tests/data)."""
    p = full_data_root() or BUNDLED_DATA
    if not (p / "kitti2015").is_dir():
        pytest.fail(f"real test data not found at {p} (bundled: {BUNDLED_DATA}; or set MCCNN_DATA)")
    return p
