#!/usr/bin/env bash
# Answers per GPU-hour (issue 55) on one 4-GPU machine, in one background job (tools/device/README.md, "work longer
# than a call"): the 12 cells of camvid_answers.toml (the presets' recipe, 3 folds x 4 seeds, 150 epochs)
#   shared: today's code, 3 cells a GPU under the pool's MPS daemon (--gpus auto --per-gpu 3 --mps on);
#   start:  the code where the issue started (0f0f21d, `git archive` unpacked in /tmp/old), one cell a GPU.
# Today's code one cell a GPU ran in a later call on a fresh machine (alone.sh): a step here that ran it failed, since
# each later call's tree replaced the repository root's untracked links that tools/device/env.sh makes (alone.sh
# works from a private copy).
# Usage, after the kit's two calls, with .device/camvid and .device/old.tar.gz carried:
#   bash tools/device/background.sh start docs/records/answers/answers.sh; then background.sh poll 580 /tmp/answers
set -u
root=$PWD
plan=$root/docs/records/answers/camvid_answers.toml
data='data.root="/tmp/camvid"'
[ -d /tmp/camvid ] || cp -r .device/camvid /tmp/camvid
mkdir -p /tmp/old /tmp/answers && tar xzf .device/old.tar.gz -C /tmp/old
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader > /tmp/answers/gpus.txt
stamp() { echo "$1 $(date +%s)" >> /tmp/answers/times.txt; }
stamp shared_start
python -m warpsense study run "$plan" --out /tmp/answers/shared --gpus auto --per-gpu 3 --mps on --set "$data" \
  > /tmp/answers/shared.log 2>&1
stamp shared_end
(cd /tmp/old && source tools/device/env.sh && python -m warpsense study run "$plan" --out /tmp/answers/start \
  --gpus auto --set "$data") > /tmp/answers/start.log 2>&1
stamp start_end
