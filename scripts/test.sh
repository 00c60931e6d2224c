#!/usr/bin/env bash
# The test command: set up everything on a fresh machine, then run the suite.
#   bash scripts/test.sh [pytest args...]
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python -m pytest -q -rfEs "$@"
