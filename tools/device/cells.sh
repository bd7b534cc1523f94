#!/usr/bin/env bash
# Runs the pending cells of a study plan on the GPU, in one process, stopped (SIGINT, resumable) after LIMIT seconds;
# the study directory .device/state/NAME (default NAME = PLAN) comes back as $OUT/NAME.tgz, without plots or weights
# but an interrupted cell's last checkpoint, so that it resumes in the next call (tools/device/README.md).
# Usage: bash tools/device/cells.sh PLAN LIMIT all|CAMERA/LIGHT/SEED [NAME]
# KEEP="CELL_DIR ..." (e.g. paste.night.seed0) brings those finished cells' last weights back too (~5 MB each).
# REUSE=".device/state/OLD ..." copies in OLD's finished runs of the same configs (`study run --reuse`, one per
# directory; carry them too).
# PER_GPU=N runs N cells at once on the GPU (the study's local pool, N worker processes; 6 at once ran slower than 1
# on an H100 without MPS: the GPU time-slices processes). Unset: the cells one after another in one process.
set -u
plan=$1; limit=$2; which=${3:-all}; name=${4:-$1}
source tools/device/env.sh
nvidia-smi --query-gpu=name --format=csv,noheader
state=.device/state/$name
mkdir -p "$state"
extra=()
[ "$which" != all ] && extra=(--cell "$which")
for old in ${REUSE:-}; do extra+=(--reuse "$old"); done
start=$(date +%s)
timeout --signal=INT --kill-after=30 "$limit" python -m warpsense study run "$plan" --out "$state" \
  --set data.root=.device/camvid ${PER_GPU:+--per-gpu "$PER_GPU"} "${extra[@]}"
rc=$?
echo "study run exit $rc after $(( $(date +%s) - start )) s"
# a finished cell's weights stay here (the device tool refuses large files, ~15 MB): only an interrupted cell's last
# checkpoint comes back, so that it can resume on the next machine
finished=()
for done in "$state"/runs/*/evaluation.json; do
  cell=$(basename "$(dirname "$done")")
  [[ " ${KEEP:-} " == *" $cell "* ]] && continue
  [ -e "$done" ] && finished+=(--exclude="$name/runs/$cell/checkpoint_last.safetensors")
done
tar czf "$OUT/$name.tgz" --exclude="*.png" --exclude="checkpoint_best.safetensors" "${finished[@]}" -C .device/state "$name"
ls -la "$OUT"
exit $rc
