#!/usr/bin/env bash
# The time-to-accuracy benchmark on the GPU: `warpsense bench --suite time-to-accuracy` for one seed (the recipe as
# shipped, then the plain-torch baseline, the presets' epochs each: 150, ~420 s on an H100), stopped after LIMIT
# seconds.
# Records and curves come back as $OUT/tta_seedS.json / .png. Usage: bash tools/device/tta.sh LIMIT SEED
set -u
limit=$1; seed=$2
source tools/device/env.sh
nvidia-smi --query-gpu=name --format=csv,noheader
timeout --signal=INT --kill-after=30 "$limit" python -m warpsense bench --suite time-to-accuracy \
  --camvid .device/camvid --device cuda --seeds "$seed" --json "$OUT/tta_seed$seed.json" --plot "$OUT/tta_seed$seed.png"
echo "bench exit $?"
