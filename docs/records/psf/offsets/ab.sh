# The PSF kernels of /tmp/src (44d3f99), /tmp/src_prev (c42ae22) and /tmp/src_old (764fa66: before flat offsets),
# each `git archive` of those commits unpacked there after the device kit's install (tools/device/README.md),
# alternating twice: docs/records/psf/variants.py's forward and forward + PSF gradient, the whole codesign camera
# (warpsense.bench.train_suite.camera_pass), then the cuda tests of the PSF op, custom ops, optics and camera, and the
# Nsight Compute profile (docs/records/psf/profile.sh). Run with tools/device/background.sh start.
set -u
R=/tmp/res7; mkdir -p $R
nvidia-smi --query-gpu=name --format=csv,noheader > $R/gpu.txt
cat > /tmp/cam.py <<'PY'
import json, sys
from warpsense.bench.train_suite import camera_pass
runs = [camera_pass("warpsense", "codesign", "cuda", 16, 352, 480, True) for _ in range(3)]
print(json.dumps({"tree": sys.argv[1], "median_ms": [r["median_ms"] for r in runs], "iqr_ms": [r["iqr_ms"] for r in runs]}))
PY
for round in 1 2; do
  (cd /tmp/src_old && source tools/device/env.sh && python docs/records/psf/variants.py --rows 8 --taps 8 > $R/old_$round.txt 2>&1; cp /tmp/psf_reference.pt /tmp/ref_old.pt)
  (cd /tmp/src && source tools/device/env.sh && python docs/records/psf/variants.py --rows 8 --taps 8 --against /tmp/ref_old.pt > $R/new_$round.txt 2>&1)
  (cd /tmp/src_prev && source tools/device/env.sh && python docs/records/psf/variants.py --rows 8 --taps 8 --against /tmp/ref_old.pt > $R/prev_$round.txt 2>&1)
  (cd /tmp/src_old && source tools/device/env.sh && python /tmp/cam.py old 2>/dev/null | tail -1) >> $R/camera.txt
  (cd /tmp/src && source tools/device/env.sh && python /tmp/cam.py new 2>/dev/null | tail -1) >> $R/camera.txt
done
grep -h rows $R/old_*.txt $R/prev_*.txt $R/new_*.txt | cut -c1-150; cat $R/camera.txt
cd /tmp/src && source tools/device/env.sh
timeout 400 python -m pytest -q -p no:warnings -m cuda tests/ops/test_psf.py tests/ops/test_custom_ops.py tests/optics tests/camera > $R/cuda_tests.txt 2>&1; echo "cuda tests exit $?"; tail -2 $R/cuda_tests.txt
OUT=$R bash docs/records/psf/profile.sh > $R/profile_summary.txt 2>&1; grep -E "psf_|Duration|Issue Slots|Registers Per|Achieved Occ" $R/profile_summary.txt
echo done
