#!/usr/bin/env bash
# Cells per GPU-hour of today's code, three cells a GPU under MPS against one a GPU, in ONE call on one 4-GPU machine
# (issue 55's test; answers.sh / alone.sh compared two calls). The 12 cells of camvid_answers.toml (the presets'
# recipe, 3 folds x 4 seeds, 150 epochs): first a 2-epoch training run, untimed, so that both studies find Warp's
# kernel cache warm; then one a GPU (--per-gpu 1 --mps off), then three a GPU (--per-gpu 3 --mps on); with the
# argument `shared`, the warm-up and three a GPU only (the pool's longest-first hand-out, measured in a later call).
# Runs from a private copy of the tree (a later call's tree replaces the repository root's files). After the kit's
# two calls with .device/camvid carried: bash tools/device/background.sh start docs/records/answers/same_call.sh, then
# background.sh poll 580 /tmp/answers (no gap between calls).
set -u
rm -rf /tmp/today && cp -r "$PWD" /tmp/today && cd /tmp/today && source tools/device/env.sh
[ -d /tmp/camvid ] || cp -r .device/camvid /tmp/camvid
mkdir -p /tmp/answers
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader > /tmp/answers/gpus.txt
stamp() { echo "$1 $(date +%s)" >> /tmp/answers/times.txt; }
data='data.root="/tmp/camvid"'
plan=docs/records/answers/camvid_answers.toml
stamp warm_start
python -m warpsense train --config camvid_codesign --set "$data" --set train.epochs=2 --set train.warmup_epochs=1 \
  --set run.output_dir='"/tmp/warm"' --no-progress > /tmp/answers/warm.log 2>&1
if [ "${1:-both}" != shared ]; then
  stamp alone_start
  python -m warpsense study run $plan --out /tmp/answers/alone --gpus auto --per-gpu 1 --mps off --set "$data" \
    > /tmp/answers/alone.log 2>&1
  stamp alone_end
fi
python -m warpsense study run $plan --out /tmp/answers/shared --gpus auto --per-gpu 3 --mps on --set "$data" \
  > /tmp/answers/shared.log 2>&1
stamp shared_end
