#!/usr/bin/env bash
# Issue 27's two unmet items, where they stand (round 29), on a machine with the kit installed
# (tools/device/install-kit.sh). Usage: bash tools/device/bound.sh eager|compiled
#   eager:    the codesign camera in parts against the Gaussian camera, with the PSF convolution's arithmetic floor
#             (tools/bench_camera_parts.py -> $OUT/camera_parts.json), then the training step, eager + one CUDA
#             graph as the presets train, of the recipe (network alone with CE, with the recipe's loss, the whole
#             step), of round 26's fastest network (projected decoder joins, 16 channels at full resolution; it
#             lost val) and of PackUNet (the packed-CFA stem) -> $OUT/step_bound_*.json, ~5 minutes
#   compiled: the whole step of the recipe and of round 26's fastest network with torch.compile (inductor,
#             train.compile = "default") and the CUDA graph -> $OUT/step_compiled_*.json, each under 270 s
set -u
test -f /tmp/site/warp/bin/warp.so || { echo "bound.sh: the kit is not installed (tools/device/install-kit.sh)"; exit 3; }
source tools/device/env.sh
nvidia-smi --query-gpu=name --format=csv,noheader
quiet() { grep -v -e Warning -e warn -e USDT; }
# step NAME VARIANTS LIMIT SET...: tools/bench_train_bound.py with the overrides SET -> $OUT/NAME.json
step() {
  local name=$1 variants=$2 limit=$3
  shift 3
  local sets=()
  for key in "$@"; do sets+=(--set "$key"); done
  timeout "$limit" python tools/bench_train_bound.py --config camvid_codesign "${sets[@]}" --variants "$variants" \
    --steps 60 --json "$OUT/$name.json" 2>&1 | quiet
  echo "$name exit ${PIPESTATUS[0]}"
}
fastest=(model.decoder_join=project model.full_width=16)
packed=(model.name=packunet model.width=22 model.full_width=0)
case "${1:-}" in
  eager)
    python tools/bench_camera_parts.py --device cuda --json "$OUT/camera_parts.json" 2>&1 | quiet
    step step_bound_recipe ce,loss,step 150
    step step_bound_project16 ce,step 120 "${fastest[@]}"
    step step_bound_packunet ce,step 120 "${packed[@]}"
    ;;
  compiled)
    step step_compiled_recipe step 270 train.compile='"default"'
    step step_compiled_project16 step 270 train.compile='"default"' "${fastest[@]}"
    ;;
  *) echo "usage: bash tools/device/bound.sh eager|compiled"; exit 2 ;;
esac
