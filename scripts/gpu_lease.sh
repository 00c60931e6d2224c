#!/usr/bin/env bash
# One device-tool call for a lent GPU machine (no network, no ../shared): the GPU
# check, then two trainings on every family at once, sized to fit one 10-minute
# command of a 15-minute lease.
#   here, first:  bash scripts/gpu_check.sh --pack-data .gpucheck/data
#                 bash scripts/pack_gpu_data.sh --families          # -> .gpu_data.tar.xz
#                 pip download pyopencl and its pure-Python needs into .gpucheck/wheels
#                 (docs/portability.md, "GPU paths and the GPU check")
#   there:        bash scripts/gpu_lease.sh [CHECK_SECONDS] [TRAIN_MINUTES]
#                 (carry [".gpucheck", ".gpu_data.tar.xz"])
# CHECK_SECONDS (default 150): gpu_check.sh --budget (0: no check).  TRAIN_MINUTES
# (default 5): each trainer's --fit-minutes; the runs share the GPU.  GPU_LEASE_RUNS
# lists them, ';'-separated NAME|ARCH|TRAINER-FLAGS, all GPU_TRAIN_SET=families
# (scripts/gpu_train.sh); the default:
#   fam_scratch|fst|                    fst from He init
#   fam_init|fst|--init kitti-fst       fst fine-tuned from the shipped kitti-fst
# (e.g. "fam_paper|paper|--init general-paper" for the accurate network).
# Evaluation on the GPU (optional), through scripts/family_table.py on --device gpu,
# one call per entry, each cut at the deadline (GPU_LEASE_DEADLINE seconds after the
# start, default 560):
#   GPU_LEASE_EVAL        ';'-separated SET|LABEL=SPEC ...: run while the trainers train
#   GPU_LEASE_EVAL_AFTER  the same, after them; {RUN} in a SPEC is the runs' folder
#                         (e.g. "heldout|p=b{RUN}/fam_paper/weights.npz@mccnn-acrt/mb")
# SET: "train" (GPU_LEASE_TRAIN_PAIRS, default 3 training pairs per dataset, from
# $GPU_TRAIN_DATA, default .gpu_data: where settings are chosen) or "heldout" (every
# pair of $GPU_LEASE_EVAL_DATA, default .gpu_eval, packed
# apart from the training data by
#   python -m tools.pack_gpu_families --holdout '*' --val $(cat runs/heldout.txt) --out .gpu_eval.tar.xz
# and carried as .gpu_eval.tar.xz).  Records: eval_train.jsonl, eval_heldout.jsonl, eval.log
# (eval2_* for GPU_LEASE_EVAL2, a second stream beside GPU_LEASE_EVAL).  The device:
# GPU_LEASE_EVAL_DEVICE (default gpu; cpu with GPU_TRAIN_DEVICE=cpu).
# What comes back ($OUT, else runs/gpu_lease; the device tool returns 8 files):
# gpu_check_report.md, gpu_check.log, per run weights.npz, history.json, log.txt, and
# the evaluation's three files (one run with the check and the evaluation, two
# runs with the check, at most two more without it).
# GPU_TRAIN_DEVICE=cpu rehearses the whole call on the CPU (gpu_check --cpu, small recipe).
set -uo pipefail
cd "$(dirname "$0")/.."
CHECK_S=${1:-150}
MIN=${2:-5}
DEST=${OUT:-runs/gpu_lease}
RUNS=${GPU_LEASE_RUNS-"fam_scratch|fst|;fam_init|fst|--init kitti-fst"}   # set and empty: no training
RUN_LIST=()
[ -n "$RUNS" ] && IFS=';' read -r -a RUN_LIST <<< "$RUNS"
for r in ${RUN_LIST[@]+"${RUN_LIST[@]}"}; do
    IFS='|' read -r name arch _ <<< "$r"
    [[ "$name" =~ ^[A-Za-z0-9._-]+$ ]] && [[ "$arch" =~ ^(fst|acrt|paper)$ ]] || {
        echo "gpu_lease: GPU_LEASE_RUNS entry '$r' is not NAME|fst, acrt or paper|FLAGS" >&2; exit 2; }
done
T_START=$SECONDS
DEADLINE=${GPU_LEASE_DEADLINE:-560}
TRAIN_PAIRS=${GPU_LEASE_TRAIN_PAIRS:-"kitti2015/e00002 kitti2015/e00004 kitti2015/e00006 middlebury/Books middlebury/Moebius middlebury/Rocks1 middlebury/trainingQ/Jadeplant middlebury/trainingQ/Playroom middlebury/trainingQ/Shelves eth3d/electro_1s eth3d/facade_1s eth3d/playground_1l"}
WORK=$(mktemp -d /tmp/gpu_lease.XXXXXX)
mkdir -p "$DEST"
export PYTHONUNBUFFERED=1
say() { echo "gpu_lease: $(date -u +%T) $*"; }

# pyopencl (the GPU image has none) from the carried wheels; the checkout importable
if ! python3 -c "import pyopencl" 2>/dev/null && ls .gpucheck/wheels/*.whl >/dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --target "$WORK/site" .gpucheck/wheels/*.whl \
        && export PYTHONPATH="$WORK/site:$PWD${PYTHONPATH:+:$PYTHONPATH}" \
        && say "pyopencl from .gpucheck/wheels"
fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>/dev/null || say "no nvidia-smi"

CPU=()
[ "${GPU_TRAIN_DEVICE:-cuda}" = cpu ] && CPU=(--cpu)
if [ "$CHECK_S" != 0 ]; then
    say "gpu_check --budget $CHECK_S ${CPU[*]}"
    TUNE=()   # GPU_LEASE_TUNE_SECONDS: mccnn-cl tune's own limit, on top of the check's budget
    [ -n "${GPU_LEASE_TUNE_SECONDS:-}" ] && TUNE=(--tune-seconds "$GPU_LEASE_TUNE_SECONDS")
    timeout $((CHECK_S + 45 + ${GPU_LEASE_TUNE_SECONDS:-0})) bash scripts/gpu_check.sh "${CPU[@]}" ${TUNE[@]+"${TUNE[@]}"} \
        --budget "$CHECK_S" --data .gpucheck/data \
        --out "$DEST/gpu_check_report.md" > "$DEST/gpu_check.log" 2>&1
    say "gpu_check exit status $? (report: gpu_check_report.md)"
fi

# unpack the data once, before the two trainers start (each would otherwise try)
if [ ! -d .gpu_data ] && [ -f .gpu_data.tar.xz ]; then
    rm -rf .gpu_data.part && mkdir -p .gpu_data.part && tar -xJf .gpu_data.tar.xz -C .gpu_data.part \
        && mv .gpu_data.part .gpu_data && say "unpacked .gpu_data.tar.xz"
fi
EVAL_DATA=${GPU_LEASE_EVAL_DATA:-.gpu_eval}     # the held-out pairs (SET heldout)
TRAIN_DATA=${GPU_TRAIN_DATA:-.gpu_data}        # the training pairs (SET train)
EVAL_DEVICE=${GPU_LEASE_EVAL_DEVICE:-gpu}      # the OpenCL device of the evaluation
[ "${GPU_TRAIN_DEVICE:-cuda}" = cpu ] && EVAL_DEVICE=${GPU_LEASE_EVAL_DEVICE:-cpu}
if [ -n "${GPU_LEASE_EVAL:-}${GPU_LEASE_EVAL2:-}${GPU_LEASE_EVAL_AFTER:-}" ] && [ "$EVAL_DATA" = .gpu_eval ] \
        && [ ! -d .gpu_eval ] && [ -f .gpu_eval.tar.xz ]; then
    rm -rf .gpu_eval.part && mkdir -p .gpu_eval.part && tar -xJf .gpu_eval.tar.xz -C .gpu_eval.part \
        && mv .gpu_eval.part .gpu_eval && say "unpacked .gpu_eval.tar.xz"
fi
evaluate() {   # ENTRIES [TAG]: ';'-separated SET|LABEL=SPEC, one after another, each cut at the deadline
    local entries tag=${2:-eval}
    IFS=';' read -r -a entries <<< "$1"
    for e in "${entries[@]}"; do
        local set=${e%%|*} method=${e#*|} left=$((DEADLINE - (SECONDS - T_START)))
        method=${method//\{RUN\}/$WORK}
        local data=$TRAIN_DATA pairs=($TRAIN_PAIRS)
        [ "$set" = heldout ] && { data=$EVAL_DATA; pairs=('*'); }
        [ "$set" = train ] || [ "$set" = heldout ] || { say "eval entry '$e': SET must be train or heldout"; continue; }
        [ "$left" -gt 10 ] || { say "eval $set $method: not run (deadline)"; continue; }
        say "eval $set $method (at most $left s)"
        timeout "$left" "${PY_EVAL[@]}" scripts/family_table.py --device "$EVAL_DEVICE" \
            --data "$data" --pairs "${pairs[@]}" --methods "$method" --out "$DEST/${tag}_$set.jsonl" \
            >> "$DEST/$tag.log" 2>&1
        say "eval $set ${method%%=*}: exit status $?"
    done
}
# the evaluation's OpenCL: a CUDA-only image registers no NVIDIA ICD (scripts/nvidia_icd.sh,
# which gpu_check.sh uses too)
. scripts/nvidia_icd.sh  # (the working directory is the repository root)
if [ "${GPU_TRAIN_DEVICE:-cuda}" != cpu ] && nvidia_icd "$WORK/vendors"; then
    say "NVIDIA ICD for the evaluation: $NVIDIA_ICD_LIB"
fi
PY_EVAL=(python3)
[ -x .venv/bin/python ] && PY_EVAL=(.venv/bin/python)
[ -n "${PYTHON:-}" ] && PY_EVAL=("$PYTHON")
LIMIT=$(python3 -c "print(int(float('$MIN') * 60 + 60))")
train() {   # NAME ARCH EXTRA-ARGS
    GPU_TRAIN_SET=families GPU_TRAIN_NAME=$1 GPU_TRAIN_ARGS=$3 OUT=$WORK \
        timeout "$LIMIT" bash scripts/gpu_train.sh "$2" "$MIN" > "$WORK/$1.out" 2>&1
    local rc=$?
    say "$1 exit status $rc"
    mkdir -p "$DEST/$1"
    local w=$WORK/$1/weights.npz
    [ -f "$w" ] || w=$WORK/$1/latest.npz
    [ -f "$w" ] && cp "$w" "$DEST/$1/weights.npz"
    [ -f "$WORK/$1/history.json" ] && cp "$WORK/$1/history.json" "$DEST/$1/"
    cp "$WORK/$1.out" "$DEST/$1/log.txt"
}
say "training ${#RUN_LIST[@]} runs at once, $MIN min each: $RUNS"
for r in ${RUN_LIST[@]+"${RUN_LIST[@]}"}; do
    IFS='|' read -r name arch flags <<< "$r"
    train "$name" "$arch" "$flags" &
done
[ -n "${GPU_LEASE_EVAL2:-}" ] && evaluate "$GPU_LEASE_EVAL2" eval2 &
[ -n "${GPU_LEASE_EVAL:-}" ] && evaluate "$GPU_LEASE_EVAL"
wait
[ -n "${GPU_LEASE_EVAL_AFTER:-}" ] && evaluate "$GPU_LEASE_EVAL_AFTER"
say "done; back: $(cd "$DEST" && find . -type f | sort | tr '\n' ' ')"
