# The PSF kernels of the work tree against those of another commit (its `git archive` as .device/src_old.tar.gz,
# unpacked in /tmp/src_old; e5c444b for the staged adjoint's records here), on one GPU after the kit's install
# (tools/device/README.md):
# docs/records/psf/variants.py's forward and forward + PSF gradient (and the staged launch's thread target: the fifth
# figure of --blocks, log2), alternating twice, each process timing each figure twice; the whole codesign camera
# (warpsense.bench.train_suite.camera_pass) of each; then the whole cuda test suite
# (the staged adjoint's call ran those of the PSF op, custom ops, optics and camera).
set -u
R=$OUT; mkdir -p /tmp/src_old && tar xzf .device/src_old.tar.gz -C /tmp/src_old
nvidia-smi --query-gpu=name --format=csv,noheader > $R/gpu.txt
cat > /tmp/cam.py <<'PY'
import json, sys
from warpsense.bench.train_suite import camera_pass
runs = [camera_pass("warpsense", "codesign", "cuda", 16, 352, 480, True) for _ in range(3)]
print(json.dumps({"tree": sys.argv[1], "median_ms": [r["median_ms"] for r in runs], "iqr_ms": [r["iqr_ms"] for r in runs]}))
PY
NEW=$PWD
for round in 1 2; do
  (cd /tmp/src_old && source tools/device/env.sh && python docs/records/psf/variants.py --rows 8 --taps 8 > $R/old_$round.txt 2>&1; cp /tmp/psf_reference.pt /tmp/ref_old.pt)
  (cd $NEW && source tools/device/env.sh && python docs/records/psf/variants.py --rows 8 --taps 8 --against /tmp/ref_old.pt \
    --blocks 128/128/5/0/17,128/128/5/0/19 > $R/new_$round.txt 2>&1)
  (cd /tmp/src_old && source tools/device/env.sh && python /tmp/cam.py old 2>/dev/null | tail -1) >> $R/camera.jsonl
  (cd $NEW && source tools/device/env.sh && python /tmp/cam.py new 2>/dev/null | tail -1) >> $R/camera.jsonl
done
grep -h rows $R/old_*.txt $R/new_*.txt | cut -c1-250; cat $R/camera.jsonl
source tools/device/env.sh
timeout 500 python -m pytest -q -p no:warnings -m cuda tests > $R/cuda_tests.txt 2>&1; echo "cuda tests exit $?"; tail -2 $R/cuda_tests.txt
