#!/usr/bin/env bash
# Call 2 of the kit (tools/device/README.md): joins the warp.so parts (part a came in call 1, under /tmp/kit),
# installs Warp into /tmp/site, checks torch + Warp on the GPU. Usage: bash tools/device/install-kit.sh [step]
set -u
cp .device/kit2/* /tmp/kit/ || exit 2
cat /tmp/kit/warp.so.xz.part_a /tmp/kit/warp.so.xz.part_b > /tmp/kit/warp.so.xz || exit 2
bash /tmp/kit/install.sh /tmp/site || exit 2
ln -sfn ../kernels warpsense/kernels; ln -sfn ../configs warpsense/configs
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
python - <<'PY'
import torch, warp as wp
wp.init()
print("torch", torch.__version__, "cuda", torch.version.cuda, "warp", wp.__version__, torch.cuda.get_device_name(0))
import warpsense
print("warpsense import ok")
PY
# the step with the Lovasz term at stride 1 and 2 (issue 27), one process each, same call
if [ "${1:-}" = step ]; then
  for s in 1 2; do
    python tools/bench_train_bound.py --config camvid_codesign --set loss.lovasz_stride=$s --steps 60 \
      --json "$OUT/step_stride$s.json" 2>&1 | grep -v Warning
  done
fi
