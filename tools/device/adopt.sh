#!/usr/bin/env bash
# The recipe's adoption study on a 4-GPU machine (issue 57; docs/records/plans/camvid_recipe_adopt.toml's header):
# each fold's clean-RGB teacher first, then the adoption plan (its "distilled" camera reads its fold's teacher from
# teachers/ beside it). Run in the background: `bash tools/device/background.sh start tools/device/adopt.sh`, then
# `bash tools/device/background.sh poll 580 /tmp/studies` from each later call (~15 minutes on 4 x H100).
set -u
root=$PWD
camvid=${CAMVID:-/tmp/camvid}
mkdir -p /tmp/studies && cd /tmp/studies || exit 1
nvidia-smi --query-gpu=name --format=csv,noheader > gpus.txt
python -m warpsense study run "$root/docs/records/plans/camvid_distill_teachers.toml" --out teachers --gpus auto \
  --set "data.root=\"$camvid\"" || exit 1
python -m warpsense study run "$root/docs/records/plans/camvid_recipe_adopt.toml" --out adopt --gpus auto --per-gpu 3 \
  --mps on --set "data.root=\"$camvid\""
