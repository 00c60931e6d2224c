#!/usr/bin/env bash
# Set up everything the tests need on a fresh Debian machine, then run them.
#   bash scripts/test.sh [pytest args...]
# Installs: Debian's PoCL (OpenCL on the CPU) and Oclgrind, a venv in .venv
# with the package (editable) and its train/dev extras, torch 2.13.0 (CPU).
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
if [ ! -e /etc/OpenCL/vendors/pocl.icd ] || ! command -v oclgrind >/dev/null; then
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq pocl-opencl-icd oclgrind >/dev/null
fi
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/pip install -q --upgrade pip >/dev/null 2>&1 || true
# torch pinned: 2.13.0 is a CPU wheel on this machine kind; unpinned pulls a 3 GB CUDA build
.venv/bin/pip install -q "torch==2.13.0" 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/pip install -q -e ".[train,dev]" 2>&1 | grep -v "^WARNING: Location" || true
exec .venv/bin/python -m pytest -q -rfEs "$@"
