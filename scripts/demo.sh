#!/usr/bin/env bash
# The main job on a fresh machine: set up (PoCL, venv, package), then match the
# bundled demo pair (MiddEval3 Adirondack, held out of training) with the shipped
# weights; prints errors beside OpenCV SGBM and writes mccnn_demo.png.
#   bash scripts/demo.sh [mccnn-cl demo options, e.g. -o out.png --force]
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/mccnn-cl demo "$@"
