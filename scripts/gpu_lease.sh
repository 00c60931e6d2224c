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
# What comes back ($OUT, else runs/gpu_lease; the device tool returns 8 files):
# gpu_check_report.md, gpu_check.log and per run weights.npz, history.json, log.txt
# (two runs with the check, at most two more without it).
# GPU_TRAIN_DEVICE=cpu rehearses the whole call on the CPU (gpu_check --cpu, small recipe).
set -uo pipefail
cd "$(dirname "$0")/.."
CHECK_S=${1:-150}
MIN=${2:-5}
DEST=${OUT:-runs/gpu_lease}
RUNS=${GPU_LEASE_RUNS:-"fam_scratch|fst|;fam_init|fst|--init kitti-fst"}
IFS=';' read -r -a RUN_LIST <<< "$RUNS"
for r in "${RUN_LIST[@]}"; do
    IFS='|' read -r name arch _ <<< "$r"
    [[ "$name" =~ ^[A-Za-z0-9._-]+$ ]] && [[ "$arch" =~ ^(fst|acrt|paper)$ ]] || {
        echo "gpu_lease: GPU_LEASE_RUNS entry '$r' is not NAME|fst, acrt or paper|FLAGS" >&2; exit 2; }
done
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
    timeout $((CHECK_S + 45)) bash scripts/gpu_check.sh "${CPU[@]}" --budget "$CHECK_S" --data .gpucheck/data \
        --out "$DEST/gpu_check_report.md" > "$DEST/gpu_check.log" 2>&1
    say "gpu_check exit status $? (report: gpu_check_report.md)"
fi

# unpack the data once, before the two trainers start (each would otherwise try)
if [ ! -d .gpu_data ] && [ -f .gpu_data.tar.xz ]; then
    rm -rf .gpu_data.part && mkdir -p .gpu_data.part && tar -xJf .gpu_data.tar.xz -C .gpu_data.part \
        && mv .gpu_data.part .gpu_data && say "unpacked .gpu_data.tar.xz"
fi
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
for r in "${RUN_LIST[@]}"; do
    IFS='|' read -r name arch flags <<< "$r"
    train "$name" "$arch" "$flags" &
done
wait
say "done; back: $(cd "$DEST" && find . -type f | sort | tr '\n' ' ')"
