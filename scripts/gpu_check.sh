#!/usr/bin/env bash
# One-call GPU check: OpenCL devices, kernel-vs-reference tests on the GPU,
# `mccnn-cl bench` with its in-run baselines, one markdown report
# (tools/gpucheck.py; docs/portability.md, "GPU paths and the GPU check").
#   bash scripts/gpu_check.sh [--cpu] [--out FILE] [--device SPEC] [--data DIR]
#                             [--wheels DIR] [--setup]
#   bash scripts/gpu_check.sh --pack-data DST   # copy the data files it reads
# No network: Python comes from .venv, else a python3 that has the package
# and its dependencies, else a venv (.gpucheck/venv, system site packages)
# filled from wheels in --wheels DIR (default .gpucheck/wheels: pyopencl and
# whatever else is missing; the package itself installed editable, so
# setuptools must be there too).  --setup runs scripts/setup.sh first (apt and
# pip: network).  Where nvidia-smi sees a GPU but no NVIDIA ICD is registered
# (CUDA-only images) and the driver's libnvidia-opencl.so.1 exists, an ICD
# folder naming it is written to .gpucheck/vendors for this run.  No GPU
# OpenCL device: one line with the likely cause, exit status 0.
set -euo pipefail
cd "$(dirname "$0")/.."
WHEELS=.gpucheck/wheels
SETUP=0
CPU=0
ARGS=()
while [ $# -gt 0 ]; do
    case "$1" in
        --wheels) WHEELS=$2; shift 2 ;;
        --setup) SETUP=1; shift ;;
        --cpu) CPU=1; ARGS+=("$1"); shift ;;
        *) ARGS+=("$1"); shift ;;
    esac
done
[ "$SETUP" = 1 ] && bash scripts/setup.sh

NEED="import mccnn_cl, numpy, pyopencl, pytest, cv2"
PY=""
NOTE=""
if [ -x .venv/bin/python ] && .venv/bin/python -c "$NEED" 2>/dev/null; then
    PY=.venv/bin/python; NOTE="the repository's .venv"
elif command -v "${PYTHON:-python3}" >/dev/null && "${PYTHON:-python3}" -c "$NEED" 2>/dev/null; then
    PY=$(command -v "${PYTHON:-python3}"); NOTE="$PY as found"
elif [ -x .gpucheck/venv/bin/python ] && .gpucheck/venv/bin/python -c "$NEED" 2>/dev/null; then
    PY=.gpucheck/venv/bin/python; NOTE=".gpucheck/venv (made earlier)"
elif [ -d "$WHEELS" ]; then
    echo "gpu_check: setting up .gpucheck/venv from the wheels in $WHEELS (no network)" >&2
    "${PYTHON:-python3}" -m venv --system-site-packages .gpucheck/venv
    VP=.gpucheck/venv/bin/python
    $VP -m pip install -q --no-index --find-links "$WHEELS" numpy pyopencl pytest opencv-python-headless tqdm >&2
    $VP -c "import setuptools, wheel" 2>/dev/null || \
        $VP -m pip install -q --no-index --find-links "$WHEELS" setuptools wheel >&2
    $VP -m pip install -q --no-index --no-deps --no-build-isolation -e . >&2
    PY=$VP; NOTE=".gpucheck/venv from the wheels in $WHEELS"
fi
if [ -z "$PY" ] || ! "$PY" -c "$NEED" 2>/dev/null; then
    echo "gpu_check: no Python with the package, numpy, pyopencl, pytest and opencv: run scripts/setup.sh (network), or give their wheels with --wheels DIR"
    exit 2
fi

# A CUDA-only image: the driver's OpenCL library is there, its ICD file is not
. scripts/nvidia_icd.sh  # (the working directory is the repository root)
if [ "$CPU" = 0 ] && nvidia_icd "$PWD/.gpucheck/vendors"; then
    NOTE="$NOTE; NVIDIA ICD written to .gpucheck/vendors for $NVIDIA_ICD_LIB (none was registered)"
    echo "gpu_check: no NVIDIA ICD registered; using $NVIDIA_ICD_LIB through .gpucheck/vendors" >&2
fi
exec "$PY" -m tools.gpucheck --env-note "$NOTE" ${ARGS[@]+"${ARGS[@]}"}
