#!/usr/bin/env bash
# Copy the labeled training pairs a GPU training run needs into one small
# folder that travels with the working tree to a machine without the shared
# data (the device tool: carry [".gpu_data"]; see docs/training.md, "On a GPU").
#   bash scripts/pack_gpu_data.sh [DATA] [DEST]
# DATA (default ../shared/data): KITTI 2012/2015 `training/` folders and
# Middlebury scenes in their official layouts.  DEST (default .gpu_data in the
# repository root, git-ignored) is emptied and refilled in the same layouts,
# so mccnn_cl.evaluation.datasets.discover reads it as it reads DATA:
#   kitti2012/training/{colored_0,colored_1,disp_occ,disp_noc}  (frames with GT)
#   kitti2015/training/{image_2,image_3,disp_occ_0,disp_noc_0}  (frames with GT)
#   middlebury/Cones/*  (the held-out Middlebury validation pair)
# No calibration files: training does not read them.  Prints the pairs found
# and the folder's size, and fails when that is 50 MiB or more (the device
# tool carries 64 MiB in all, the working tree included).
#   bash scripts/pack_gpu_data.sh --families [ARGS]
# packs every family instead (tools/pack_gpu_families.py: training pairs but
# general-fst's held-out families, one validation pair per dataset, gray
# images, ground truth rounded to 1/32 px) into .gpu_data.tar.xz, for
# GPU_TRAIN_SET=families bash scripts/gpu_train.sh.
set -euo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
if [ "${1:-}" = --families ]; then
    shift
    PY=python3
    [ -x "$REPO/.venv/bin/python" ] && PY=$REPO/.venv/bin/python
    exec "$PY" "$REPO/tools/pack_gpu_families.py" "$@"
fi
DATA=${1:-$REPO/../shared/data}
DEST=${2:-$REPO/.gpu_data}
LIMIT_MIB=50

[ -d "$DATA" ] || { echo "pack_gpu_data: no data folder at $DATA" >&2; exit 2; }
DATA=$(cd "$DATA" && pwd)
case "$(basename "$DEST")" in
    ""|"/"|".") echo "pack_gpu_data: refusing destination $DEST" >&2; exit 2 ;;
esac
rm -rf "$DEST"
mkdir -p "$DEST"

# copy_kitti KIND LEFT RIGHT GT...: frames of DATA/KIND/training whose GT exists
copy_kitti() {
    local kind=$1 left=$2 right=$3
    shift 3
    local src=$DATA/$kind/training dst=$DEST/$kind/training n=0 f frame gt have
    [ -d "$src/$left" ] || { echo "pack_gpu_data: $src/$left missing" >&2; exit 2; }
    for f in "$src/$left"/*_10.png; do
        [ -e "$f" ] || continue
        frame=$(basename "$f")
        have=0
        for gt in "$@"; do [ -e "$src/$gt/$frame" ] && have=1; done
        [ "$have" = 1 ] || continue
        [ -e "$src/$right/$frame" ] || { echo "pack_gpu_data: $src/$right/$frame missing" >&2; exit 2; }
        for d in "$left" "$right" "$@"; do
            if [ -e "$src/$d/$frame" ]; then
                mkdir -p "$dst/$d"
                cp -p "$src/$d/$frame" "$dst/$d/"
            fi
        done
        n=$((n + 1))
    done
    [ "$n" -gt 0 ] || { echo "pack_gpu_data: no labeled frame in $src" >&2; exit 2; }
    echo "$kind: $n frames"
}

copy_kitti kitti2012 colored_0 colored_1 disp_occ disp_noc
copy_kitti kitti2015 image_2 image_3 disp_occ_0 disp_noc_0
[ -f "$DATA/middlebury/Cones/im0.png" ] || { echo "pack_gpu_data: $DATA/middlebury/Cones missing" >&2; exit 2; }
mkdir -p "$DEST/middlebury"
cp -rp "$DATA/middlebury/Cones" "$DEST/middlebury/"
echo "middlebury: Cones"

KIB=$(du -sk "$DEST" | cut -f1)
echo "packed $DATA -> $DEST: $(du -sh "$DEST" | cut -f1) ($KIB KiB, $(find "$DEST" -type f | wc -l) files)"
if [ "$KIB" -ge $((LIMIT_MIB * 1024)) ]; then
    echo "pack_gpu_data: $DEST is ${KIB} KiB, over the ${LIMIT_MIB} MiB limit" >&2
    exit 1
fi
