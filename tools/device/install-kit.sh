#!/usr/bin/env bash
# Call 2 of the kit (tools/device/README.md): joins the warp.so parts (part a came in call 1, under /tmp/kit),
# installs Warp into /tmp/site, checks torch + Warp on the GPU, then runs the mode's cuda tests or benchmark.
# Usage: bash tools/device/install-kit.sh [data|smooth|render|psf|upsample|bn|gate|loss|network|train]
#   data:     the training data path's cuda tests (scale fill, copy-paste on the GPU), ~1 minute
#   smooth:   the fused edge-aware smoothness op's cuda tests
#   render:   the lens rendering's cuda tests (tests/optics)
#   psf:      the PSF op's cuda tests, then tools/bench_psf.py -> $OUT/psf.json
#   upsample: the fused decoder join's cuda tests (and the networks')
#   bn:       the fused batch norm + ReLU's cuda tests (and the networks', the bitwise-repeat training test)
#   gate:     the fused squeeze-and-excitation gate's cuda tests (and the batch norm's, the networks', the training
#             tests)
#   loss:     the loss ops' cuda tests (softmax + cross-entropy, Lovasz, smoothness; the losses', the training tests)
#   network:  the networks' cuda tests (and the batch norm, gate and decoder join ops')
#   train:    `warpsense bench --suite train` on the GPU: the training step, the camera alone and batch-1 latency
#             (eager, camera cached, graph replay) against the plain-torch baseline -> $OUT/bench_train.json
# Each mode's test output is in $OUT/<mode>_cuda_tests.txt. A fused op against its torch form, in the training step
# and batch-1 latency (an A/B in one process), in a later call: `source tools/device/env.sh; python
# tools/device/ab.py SWITCH warpsense/__main__.py bench --suite train --device cuda --json "$OUT/train_SWITCH.json"`
# for SWITCH fused and, e.g., torch-norm.
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
quiet() { grep -v -e Warning -e warn -e USDT; }
case "${1:-}" in
  "") ;;
  data) cuda_tests data_cuda_tests 240 tests/data/test_on_device.py ;;
  smooth) cuda_tests smooth_cuda_tests 240 tests/ops/test_smoothness.py tests/ops/test_custom_ops.py -k smooth ;;
  render) cuda_tests render_cuda_tests 200 tests/optics ;;
  psf)
    cuda_tests psf_cuda_tests 240 tests/ops/test_psf.py tests/ops/test_custom_ops.py
    python tools/bench_psf.py --device cuda --json "$OUT/psf.json" 2>&1 | quiet
    ;;
  upsample) cuda_tests upsample_cuda_tests 240 tests/ops/test_upsample.py tests/ops/test_custom_ops.py tests/models ;;
  bn)
    cuda_tests bn_cuda_tests 240 tests/ops/test_batchnorm.py tests/ops/test_custom_ops.py tests/models \
      tests/train/test_training.py
    ;;
  gate)
    cuda_tests gate_cuda_tests 240 tests/ops/test_gate.py tests/ops/test_batchnorm.py tests/ops/test_custom_ops.py \
      tests/models tests/train/test_training.py
    ;;
  loss)
    cuda_tests loss_cuda_tests 300 tests/ops/test_cross_entropy.py tests/ops/test_lovasz.py \
      tests/ops/test_smoothness.py tests/ops/test_custom_ops.py tests/train/test_losses.py tests/train/test_training.py
    ;;
  network)
    cuda_tests network_cuda_tests 300 tests/models tests/ops/test_batchnorm.py tests/ops/test_gate.py \
      tests/ops/test_upsample.py
    ;;
  train) python -m warpsense bench --suite train --device cuda --json "$OUT/bench_train.json" 2>&1 | quiet ;;
  *) echo "usage: bash tools/device/install-kit.sh [data|smooth|render|psf|upsample|bn|gate|loss|network|train]" >&2
     exit 2 ;;
esac
