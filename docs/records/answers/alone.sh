#!/usr/bin/env bash
# The same 12 cells with today's code one cell a GPU (--per-gpu 1, no MPS), while nvidia-smi records each worker's
# memory; then the memory of one training process at batch 16 and 32 (docs/records/answers/memory.py). Runs from a
# private copy of the tree (a later call's tree replaces the repository root's files). After answers.sh's kit calls,
# .device/camvid in /tmp/camvid: bash tools/device/background.sh start docs/records/answers/alone.sh
set -u
rm -rf /tmp/today && cp -r "$PWD" /tmp/today && cd /tmp/today && source tools/device/env.sh
[ -d /tmp/camvid ] || cp -r .device/camvid /tmp/camvid
mkdir -p /tmp/answers
nvidia-smi --query-compute-apps=pid,used_memory --format=csv,noheader,nounits -l 2 > /tmp/answers/alone_memory.txt &
sampler=$!
echo "alone_start $(date +%s)" >> /tmp/answers/times.txt
python -m warpsense study run docs/records/answers/camvid_answers.toml --out /tmp/answers/alone --gpus auto --per-gpu 1 \
  --mps off --set 'data.root="/tmp/camvid"' > /tmp/answers/alone.log 2>&1
echo "alone_end $(date +%s)" >> /tmp/answers/times.txt
kill $sampler
CUDA_VISIBLE_DEVICES=0 python docs/records/answers/memory.py 16 352 480 > /tmp/answers/memory16.json 2>/tmp/answers/memory16.err &
CUDA_VISIBLE_DEVICES=1 python docs/records/answers/memory.py 32 352 480 > /tmp/answers/memory32.json 2>/tmp/answers/memory32.err &
wait
