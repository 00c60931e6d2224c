#!/usr/bin/env bash
# The test command: set up everything on a fresh machine, then run the suite.
#   bash scripts/test.sh [pytest args...]
# Besides scripts/setup.sh (PoCL, Oclgrind, the venv), installs Mesa's Rusticl
# (apt mesa-opencl-icd) and writes the single-implementation .icd files that
# tests/test_oclgrind.py and tests/test_portability.py use
# (scripts/opencl_impls.sh; see docs/portability.md).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/opencl_impls.sh pocl oclgrind rusticl >/dev/null
exec .venv/bin/python -m pytest -q -rfEs "$@"
