#!/usr/bin/env bash
# Idempotent set-up on a fresh Debian machine: OpenCL on the CPU (Debian's PoCL),
# Oclgrind (used by the tests), a venv in .venv with the package (editable) and
# its train/dev extras.  torch is pinned to 2.13.0: on this machine kind that is a
# CPU wheel on local disk, while an unpinned torch pulls a 3 GB CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
if [ ! -e /etc/OpenCL/vendors/pocl.icd ] || ! command -v oclgrind >/dev/null; then
    echo "setup: installing pocl-opencl-icd and oclgrind (apt)" >&2
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq pocl-opencl-icd oclgrind >/dev/null
fi
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
# Installed already? Found without importing torch (~2 s an import here), so a set-up run
# that has nothing to do takes a fraction of a second.
FOUND='import importlib.util as u, sys
sys.exit(0 if all(u.find_spec(m) for m in "mccnn_cl mccnn_cl.kernels mccnn_cl.train torch pytest wheel pyopencl cv2 dask distributed hypothesis".split()) else 1)'
if ! .venv/bin/python -c "$FOUND" 2>/dev/null; then
    echo "setup: installing the package into .venv" >&2
    .venv/bin/pip install -q "torch==2.13.0" 2>&1 | grep -v "^WARNING: Location" || true
    .venv/bin/pip install -q -e ".[train,dev]" 2>&1 | grep -v -E "^WARNING: Location|^ +|^$|!!" || true
    .venv/bin/python -c "import mccnn_cl, torch, pytest, pyopencl, dask, distributed, hypothesis"  # fail loudly if incomplete
fi
# The package's bytecode, written once here: where PYTHONDONTWRITEBYTECODE is set (these VMs set it),
# every mccnn-cl process would otherwise compile ~45 modules from source (~0.07 s a start).  Stale files
# after an edit are only ignored, never wrong.
.venv/bin/python -m compileall -q mccnn_cl >/dev/null || true
