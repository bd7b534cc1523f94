#!/usr/bin/env bash
# Call 2 of the kit (tools/device/README.md): joins the warp.so parts (part a came in call 1, under /tmp/kit),
# installs Warp into /tmp/site, checks torch + Warp on the GPU. Usage: bash tools/device/install-kit.sh [step|smooth|data|render|psf|upsample|round23|bn|gate|loss|network|latency|bound]
#   step:   the training step at Lovasz stride 1 and 2 (round 16)
#   smooth: the fused smoothness op's cuda tests, then the step with and without the smoothness term (what the term
#           costs now; round 15 measured ~2.9 ms of 51 for its plain-torch form)
#   data:   the training data path's cuda tests (scale fill, copy-paste on the GPU), ~1 minute
#   render: the lens rendering's cuda tests, then tools/bench_render.py on the GPU (float32 with the whole camera,
#           float64) -> $OUT/render_*.json, ~2 minutes (issue 27)
#   psf:    the PSF op's cuda tests, then tools/bench_psf.py, the codesign camera (tools/bench_render.py --camera)
#           and the training step -> $OUT/psf.json, camera.json, step.json, ~3 minutes (issue 27)
#   upsample: the fused decoder join's cuda tests, tools/bench_upsample.py, then the step without and with it
#           (tools/device/ab.py torch-joins for the first) -> $OUT/step_fused_{off,on}.json, ~3 minutes (issue 27)
#   round23: the cuda tests of the PSF op, the decoder join and the networks, then batch-1 latency, the camera alone,
#           the training step and the joins, as the code stands -> $OUT/*.json, *.txt, ~5 minutes (issue 27)
#   bn:     the fused batch norm + ReLU's cuda tests (and the networks', the bitwise-repeat training test), then the
#           step with torch's batch norm and ReLU (tools/device/ab.py torch-norm) and with the op, the latter profiled
#           -> $OUT/step_bn_{off,on}.json, bn_profile.tar.gz, ~6 minutes (issue 27)
#   gate:   the fused squeeze-and-excitation gate's cuda tests (and the networks', the training tests), then the step
#           and batch-1 latency with the gate through torch and through the op (tools/device/ab.py)
#           -> $OUT/step_gate_{off,on}.json, latency_gate_{off,on}.json, ~6 minutes (issue 27)
#   loss:   the loss ops' cuda tests (softmax + cross-entropy, Lovasz, smoothness; the losses', the training tests),
#           the loss terms (tools/bench_loss.py, the fused loss profiled), then the step with all the loss's ops in
#           torch form, with the fused softmax off, with the Lovasz op off, and as shipped (tools/device/ab.py)
#           -> $OUT/loss_terms.json, loss_profile.txt, step_loss_{torch,nosoftmax,nolovasz,fused}.json, ~7 minutes
#           (issue 27, round 25)
#   network: the networks' cuda tests (and the batch-norm and gate ops'), then the training step of the network
#           candidates (tools/bench_train_bound.py: the recipe, full_width 16, projected decoder joins, both, and
#           both at full_width 12) -> $OUT/network_cuda_tests.txt, step_net_*.json, ~6 minutes (issue 27, round 26)
#   latency: batch-1 latency (tools/bench_latency.py: the eager calls of the three systems and of warpsense's two
#           with the camera cached, interleaved, each paired by round with the baseline; graph replay), each
#           system's host time by Python function (cProfile), the camera ops' custom-op dispatch
#           (tools/bench_dispatch.py) -> $OUT/latency.json, latency_host.tar.gz, dispatch.txt, ~2 minutes (round 27)
#   bound:  tools/device/bound.sh eager (the camera in parts, the step of the recipe and of two faster networks;
#           round 29), ~5 minutes
set -u
cp .device/kit2/* /tmp/kit/ || exit 2
cat /tmp/kit/warp.so.xz.part_a /tmp/kit/warp.so.xz.part_b > /tmp/kit/warp.so.xz || exit 2
bash /tmp/kit/install.sh /tmp/site || exit 2
source tools/device/env.sh
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
python - <<'PY'
import torch, warp as wp
wp.init()
print("torch", torch.__version__, "cuda", torch.version.cuda, "warp", wp.__version__, torch.cuda.get_device_name(0))
import warpsense
print("warpsense import ok")
PY
# cuda_tests NAME LIMIT PATH...: the cuda-marked tests of PATH... -> $OUT/NAME.txt, their exit status and summary
cuda_tests() {
  local name=$1 limit=$2
  shift 2
  timeout "$limit" python -m pytest -q -p no:warnings -m cuda "$@" > "$OUT/$name.txt" 2>&1
  echo "$name exit $?"; tail -2 "$OUT/$name.txt"
}
# camera_bench OUT: the codesign camera forward + backward with the rendering in place, and the baseline's camera
camera_bench() {
  python tools/bench_render.py --device cuda --camera --json "$1" 2>&1 | grep -v -e Warning -e USDT
}
# step_bench OUT: the codesign training step (network alone and whole, tools/bench_train_bound.py)
step_bench() {
  python tools/bench_train_bound.py --config camvid_codesign --steps 60 --json "$1" 2>&1 | grep -v Warning
}
# the step with the Lovasz term at stride 1 and 2 (issue 27), one process each, same call
if [ "${1:-}" = step ]; then
  for s in 1 2; do
    python tools/bench_train_bound.py --config camvid_codesign --set loss.lovasz_stride=$s --steps 60 \
      --json "$OUT/step_stride$s.json" 2>&1 | grep -v Warning
  done
fi
if [ "${1:-}" = smooth ]; then
  python -m pytest -q -p no:warnings -m cuda tests/ops/test_smoothness.py tests/ops/test_custom_ops.py -k smooth
  # $OUT names without '=': the device tool refuses such names on the way back
  for w in on:0.01 off:0; do
    python tools/bench_train_bound.py --config camvid_codesign --set "loss.smooth_weight=${w#*:}" --steps 60 \
      --json "$OUT/step_smooth_${w%%:*}.json" 2>&1 | grep -v Warning
  done
fi
if [ "${1:-}" = data ]; then
  python -m pytest -q -p no:warnings -m cuda tests/data/test_on_device.py
fi
if [ "${1:-}" = render ]; then
  cuda_tests render_cuda_tests 200 tests/optics
  camera_bench "$OUT/render_float32.json"
  python tools/bench_render.py --device cuda --dtype float64 --json "$OUT/render_float64.json" 2>&1 | grep -v -e Warning -e USDT
fi
if [ "${1:-}" = psf ]; then
  cuda_tests psf_cuda_tests 240 tests/ops/test_psf.py tests/ops/test_custom_ops.py
  python tools/bench_psf.py --device cuda --json "$OUT/psf.json" 2>&1 | grep -v -e Warning -e USDT
  camera_bench "$OUT/camera.json"
  step_bench "$OUT/step.json"
fi
if [ "${1:-}" = upsample ]; then
  cuda_tests upsample_cuda_tests 240 tests/ops/test_upsample.py tests/ops/test_custom_ops.py tests/models
  python tools/bench_upsample.py --device cuda 2>&1 | grep -v Warning | tee "$OUT/upsample_joins.txt"
  for ab in off:torch-joins on:fused; do
    python tools/device/ab.py "${ab#*:}" tools/bench_train_bound.py --config camvid_codesign --steps 60 \
      --json "$OUT/step_fused_${ab%%:*}.json" 2>&1 | grep -v Warning
  done
fi
if [ "${1:-}" = bn ]; then
  cuda_tests bn_cuda_tests 240 tests/ops/test_batchnorm.py tests/ops/test_custom_ops.py tests/models \
    tests/train/test_training.py
  for ab in off:torch-norm on:fused; do
    profile=()
    [ "${ab%%:*}" = on ] && profile=(--profile /tmp/bn_profile)
    python tools/device/ab.py "${ab#*:}" tools/bench_train_bound.py --config camvid_codesign --steps 60 \
      --json "$OUT/step_bn_${ab%%:*}.json" "${profile[@]}" 2>&1 | grep -v Warning
  done
  tar czf "$OUT/bn_profile.tar.gz" -C /tmp bn_profile
fi
if [ "${1:-}" = gate ]; then
  cuda_tests gate_cuda_tests 240 tests/ops/test_gate.py tests/ops/test_batchnorm.py tests/ops/test_custom_ops.py \
    tests/models tests/train/test_training.py
  for ab in off:torch-gate on:fused; do
    python tools/device/ab.py "${ab#*:}" tools/bench_train_bound.py --config camvid_codesign --steps 60 \
      --json "$OUT/step_gate_${ab%%:*}.json" 2>&1 | grep -v -e Warning -e warn
  done
  for ab in off:torch-gate on:fused; do
    python tools/device/ab.py "${ab#*:}" tools/bench_latency.py --device cuda --json "$OUT/latency_gate_${ab%%:*}.json" \
      2>&1 | grep -v -e Warning -e USDT -e warn
  done
fi
if [ "${1:-}" = round23 ]; then
  cuda_tests cuda_tests 300 tests/ops/test_psf.py tests/ops/test_upsample.py tests/ops/test_custom_ops.py tests/models
  python tools/bench_latency.py --device cuda --json "$OUT/latency.json" 2>&1 | grep -v -e Warning -e USDT
  camera_bench "$OUT/camera.json"
  step_bench "$OUT/step.json"
  python tools/bench_upsample.py --device cuda 2>&1 | grep -v Warning > "$OUT/upsample_joins.txt"
fi
if [ "${1:-}" = loss ]; then
  cuda_tests loss_cuda_tests 300 tests/ops/test_cross_entropy.py tests/ops/test_lovasz.py tests/ops/test_smoothness.py \
    tests/ops/test_custom_ops.py tests/train/test_losses.py tests/train/test_training.py
  python tools/bench_loss.py --device cuda --json "$OUT/loss_terms.json" --profile "$OUT/loss_profile.txt" 2>&1 \
    | grep -v -e Warning -e USDT
  for ab in torch:torch-loss nosoftmax:torch-softmax nolovasz:torch-lovasz fused:fused; do
    python tools/device/ab.py "${ab#*:}" tools/bench_train_bound.py --config camvid_codesign --steps 60 \
      --json "$OUT/step_loss_${ab%%:*}.json" 2>&1 | grep -v -e Warning -e warn
  done
fi
if [ "${1:-}" = network ]; then
  cuda_tests network_cuda_tests 300 tests/models tests/ops/test_batchnorm.py tests/ops/test_gate.py \
    tests/ops/test_upsample.py
  for candidate in recipe: full16:model.full_width=16 project:model.decoder_join=project \
      project_full16:model.decoder_join=project,model.full_width=16 \
      project_full12:model.decoder_join=project,model.full_width=12; do
    sets=()
    IFS=, read -ra keys <<< "${candidate#*:}"
    for key in "${keys[@]}"; do sets+=(--set "$key"); done
    python tools/bench_train_bound.py --config camvid_codesign "${sets[@]}" --steps 60 \
      --json "$OUT/step_net_${candidate%%:*}.json" 2>&1 | grep -v -e Warning -e warn
  done
fi
if [ "${1:-}" = latency ]; then
  python tools/bench_latency.py --device cuda --repeats 200 --json "$OUT/latency.json" \
    --host-profile /tmp/latency_host 2>&1 | grep -v -e Warning -e USDT -e warn
  tar czf "$OUT/latency_host.tar.gz" -C /tmp latency_host
  python tools/bench_dispatch.py --device cuda 2>&1 | grep -v -e Warning -e USDT -e warn | tee "$OUT/dispatch.txt"
fi
if [ "${1:-}" = bound ]; then
  bash tools/device/bound.sh eager
fi
