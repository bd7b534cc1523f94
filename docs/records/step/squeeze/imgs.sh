#!/bin/bash
# img/s of the recipe's training with and without squeeze-excitation, alternating, 10 epochs each (4 warm-up).
cd /tmp/src && source tools/device/env.sh
mkdir -p /tmp/img $OUT/img
for pass in 1 2; do for sq in true false; do
  python -m warpsense train --config camvid_codesign --set 'data.root="/tmp/camvid"' --set model.squeeze=$sq \
    --set train.epochs=10 --set train.warmup_epochs=4 --set "run.output_dir=\"/tmp/img/$sq$pass\"" --no-progress \
    --set run.seed=0 > /tmp/img/$sq$pass.log 2>&1
  cp /tmp/img/$sq$pass/*/metrics.jsonl $OUT/img/metrics_$sq$pass.jsonl; grep -h "parameters" /tmp/img/$sq$pass.log
done; done
nvidia-smi --query-gpu=name --format=csv,noheader > $OUT/img/gpu.txt
