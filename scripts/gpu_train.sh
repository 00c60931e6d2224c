#!/usr/bin/env bash
# One-command training run on a lent GPU machine (no network, no ../shared):
#   bash scripts/pack_gpu_data.sh                 # here, first: the data -> .gpu_data/
#   bash scripts/gpu_train.sh [ARCH] [MINUTES]    # there, from the repository root
# ARCH: fst (default), acrt or paper.  MINUTES (default 8): the trainer's wall
# time; it times a few steps (--fit-minutes, mccnn_cl/train/budget.py) and picks the
# number of epochs so that the whole lr schedule ends in time.  Trains on the
# 11 KITTI pairs of .gpu_data with kitti2015/000000 and middlebury/Cones held
# out, with a GPU-sized crop recipe, into $OUT/gpu_ARCH when $OUT is set (the
# device tool's output folder), else runs/gpu_ARCH: weights.npz, best.npz,
# history.json, training.png, run.json, checkpoint.pt, log.txt.
# Environment:
#   GPU_TRAIN_DEVICE  torch device (default cuda; with no CUDA device the
#                     script stops with one line); "cpu" rehearses the whole
#                     run on the CPU with a small recipe and .venv/bin/python
#   GPU_TRAIN_DATA    data folder (default .gpu_data; when it is missing and
#                     DATA.tar.xz exists, that archive is unpacked into it)
#   GPU_TRAIN_SET     kitti (default: the 11 KITTI pairs, as above) or
#                     families: every packed pair but general-fst's held-out
#                     scene families (tools/pack_gpu_families.py packs them:
#                     `bash scripts/pack_gpu_data.sh --families`, carry
#                     [".gpu_data.tar.xz"]), with general-fst's mixed-data
#                     choices (dataset balance, family augmentation and offsets)
#   GPU_TRAIN_NAME    run folder name (default gpu_ARCH; two runs at once need two)
#   GPU_TRAIN_ARGS    extra trainer flags, appended (they override the recipe's)
#   PYTHON            interpreter (default .venv/bin/python if it has torch, else python3)
# mccnn_cl is made importable without network: already importable, else
# `pip install --no-deps --no-index --no-build-isolation -e .`, else the
# checkout itself on PYTHONPATH (mccnn_cl/train is inside the package).
# Training never imports pyopencl (tests/test_gpu_train_script.py).
set -euo pipefail
cd "$(dirname "$0")/.."
REPO=$PWD
ARCH=${1:-fst}
MINUTES=${2:-8}
DEV=${GPU_TRAIN_DEVICE:-cuda}
DATA=${GPU_TRAIN_DATA:-.gpu_data}
SET=${GPU_TRAIN_SET:-kitti}
export PYTHONUNBUFFERED=1  # the log is whole even when the device tool stops the command at its limit
say() { echo "gpu_train: $*"; }
die() { echo "gpu_train: $*" >&2; exit "${2:-2}"; }

case "$ARCH" in fst|acrt|paper) ;; *) die "ARCH must be fst, acrt or paper, got '$ARCH'" ;; esac
[[ "$MINUTES" =~ ^[0-9]+([.][0-9]+)?$ ]] || die "MINUTES must be a number, got '$MINUTES'"
case "$SET" in kitti|families) ;; *) die "GPU_TRAIN_SET must be kitti or families, got '$SET'" ;; esac
NAME=${GPU_TRAIN_NAME:-gpu_$ARCH}
[[ "$NAME" =~ ^[A-Za-z0-9._-]+$ ]] || die "GPU_TRAIN_NAME must be letters, digits, '.', '_' or '-', got '$NAME'"

if [ -n "${PYTHON:-}" ]; then
    PY=$PYTHON
elif [ -x .venv/bin/python ] && .venv/bin/python -c "import torch" 2>/dev/null; then
    PY=.venv/bin/python
else
    PY=python3
fi
"$PY" -c "import torch, numpy, cv2" 2>/dev/null || \
    die "$PY lacks torch, numpy or opencv-python-headless (needed to train)"

if [[ "$DEV" == cuda* ]]; then
    if ! "$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" 2>/dev/null; then
        SMI=$( (nvidia-smi -L 2>/dev/null | head -1) || true)
        die "no CUDA device for torch $("$PY" -c 'import torch; print(torch.__version__)' 2>/dev/null) (nvidia-smi: ${SMI:-none}); this is for a GPU machine — rehearse on the CPU with GPU_TRAIN_DEVICE=cpu" 3
    fi
fi
if [ ! -d "$DATA" ] && [ -f "$DATA.tar.xz" ]; then
    mkdir -p "$DATA.part" && tar -xJf "$DATA.tar.xz" -C "$DATA.part" && mv "$DATA.part" "$DATA" || \
        die "cannot unpack $DATA.tar.xz"
    say "unpacked $DATA.tar.xz into $DATA"
fi
[ -d "$DATA" ] || die "no data at $DATA: run scripts/pack_gpu_data.sh first (and carry [\".gpu_data\"] to the GPU machine)"

# mccnn_cl importable (the training entry point needs no pyopencl)
RUN_TRAIN=("$PY" -m mccnn_cl.train.train)
HOW="installed"
if ! "$PY" -c "import mccnn_cl.train.train" 2>/dev/null; then
    if "$PY" -m pip install -q --no-deps --no-index --no-build-isolation -e . >/dev/null 2>&1 \
            && "$PY" -c "import mccnn_cl.train.train" 2>/dev/null; then
        HOW="pip install -e . (no network)"
    else
        export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}"
        "$PY" -c "import mccnn_cl.train.train" || die "cannot import mccnn_cl.train.train with $PY"
        HOW="PYTHONPATH=$REPO (pip install -e failed)"
    fi
fi

# The recipe: crops of 63x63 features, 32 per step, the KITTI augmentation, sub-pixel offsets
RECIPE=(--sampler crop --augment --subpixel --crops-per-step 32 --crop 63 63 --per-crop 2048
        --steps-per-epoch 500 --lr-steps 0.8 0.95)
case "$ARCH" in
    fst) RECIPE+=(--negatives 4) ;;     # dot-product head: extra negatives are almost free
    acrt) RECIPE+=(--negatives 2) ;;    # fc head runs per example
    paper) RECIPE+=(--negatives 1) ;;
esac
if [ "$SET" = kitti ]; then
    PAIRS=(--include 'kitti*' --holdout kitti2015/000000 middlebury/Cones)
else   # the pack holds no pair of general-fst's held-out families (docs/training.md) but these
    # four, one per dataset, for validation; general-fst's mixed-data choices
    PAIRS=(--include '*' --holdout kitti2015/000000 middlebury/Cones middlebury/trainingQ/Piano
           eth3d/delivery_area_1l)
    RECIPE+=(--augment-preset family --family-offsets --balance dataset --max-per-pair 200000)
fi
if [ "$DEV" = cpu ]; then   # rehearsal: the same path, a recipe 2 CPU cores get through in a minute
    RECIPE+=(--crops-per-step 2 --crop 31 31 --per-crop 256 --steps-per-epoch 50
             --val-pixels 300 --val-examples 400 --calibrate-steps 5 --threads 2)
fi
# shellcheck disable=SC2206
EXTRA=(${GPU_TRAIN_ARGS:-})

if [ -n "${OUT:-}" ]; then RUN="$OUT/$NAME"; else RUN="runs/$NAME"; fi
rm -rf "$RUN"
mkdir -p "$RUN"

run() {
    say "$(date -u +%FT%TZ), arch $ARCH, set $SET, $MINUTES min, device $DEV, python $PY ($HOW), run folder $RUN"
    if [[ "$DEV" == cuda* ]]; then
        nvidia-smi --query-gpu=name,memory.total,memory.used,driver_version --format=csv 2>/dev/null || say "nvidia-smi not found"
    else
        say "REHEARSAL on the CPU (GPU_TRAIN_DEVICE=$DEV): small recipe, not a GPU run"
    fi
    "$PY" - "$DEV" <<'EOF'
import os, sys, torch
dev = sys.argv[1]
print(f"torch {torch.__version__}, CUDA {torch.version.cuda}, cuDNN {torch.backends.cudnn.version()}, "
      f"{os.cpu_count()} CPUs, {torch.get_num_threads()} torch threads")
if dev.startswith("cuda"):
    p = torch.cuda.get_device_properties(torch.device(dev))
    print(f"{dev}: {p.name}, {p.total_memory / 2**30:.1f} GiB, compute capability {p.major}.{p.minor}, "
          f"{p.multi_processor_count} SMs")
EOF
    local t0=$SECONDS
    local cmd=("${RUN_TRAIN[@]}" --data "$DATA" "${PAIRS[@]}"
               --arch "$ARCH" "${RECIPE[@]}" --device "$DEV" --fit-minutes "$MINUTES" --no-progress
               --out "$RUN" ${EXTRA[@]+"${EXTRA[@]}"})
    echo "+ $(printf "%q " "${cmd[@]}")"
    "${cmd[@]}"
    local rc=$?
    [ "$rc" = 0 ] || { say "the trainer failed (exit status $rc) after $((SECONDS - t0)) s"; return "$rc"; }
    say "trainer finished in $((SECONDS - t0)) s"
    # weights.npz is the net after the last epoch, as latest.npz: one copy comes back
    [ -f "$RUN/weights.npz" ] && rm -f "$RUN/latest.npz"
    if [ -f "$RUN/checkpoint.pt" ] && [ "$(du -k "$RUN/checkpoint.pt" | cut -f1)" -gt 16000 ] && [ -n "${OUT:-}" ]; then
        say "checkpoint.pt over 16 MB: removed (the device tool would not bring it back)"
        rm -f "$RUN/checkpoint.pt"
    fi
    "$PY" - "$RUN" <<'EOF'
import json, sys
from pathlib import Path
from mccnn_cl.weights import Weights
run = Path(sys.argv[1])
w = Weights.load(str(run / "weights.npz"))
t = w.meta.get("training", {})
fit = t.get("fit_minutes", {})
print(f"weights.npz: {w.architecture}, conv {w.conv_layers()}, fc {w.fc_layers()}; {t.get('epochs')} epochs x "
      f"{fit.get('steps_per_epoch')} steps, {t.get('examples')} examples, {t.get('wall_time_s')} s of training")
h = json.loads((run / "history.json").read_text())
for r in h:
    per = r.get("val_err3_per_pair") or {}
    print(f"epoch {r['epoch']:3d}  train loss {r['train_loss']:.4f}  val loss {r.get('val_loss', float('nan')):.4f}  "
          f"WTA 3-px " + "  ".join(f"{k} {100 * v:.1f} %" for k, v in per.items())
          + f"  {r['examples_per_s']:.0f} ex/s")
EOF
    ls -l "$RUN"
}
set +e
run 2>&1 | tee "$RUN/log.txt"
RC=${PIPESTATUS[0]}
set -e
[ "$RC" = 0 ] || die "the run failed (exit status $RC); see $RUN/log.txt" "$RC"
say "done: $RUN (check here: mccnn-cl match L.png R.png -o d.png --weights $RUN/weights.npz)"
