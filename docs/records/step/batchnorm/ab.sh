# src_old: `git archive cc8f8ce` (the commit before the batch-norm change), src: d87ddec; unpacked under /tmp after the device kit's install
set -u
R=/tmp/res10; mkdir -p $R
cp /tmp/src/docs/records/step/batchnorm/ab.py /tmp/ab.py
for round in 1 2; do
  for tree in src_old src; do
    (cd /tmp/$tree && source tools/device/env.sh && python /tmp/ab.py $tree 2>/dev/null | tail -1) >> $R/ab.jsonl
  done
done
cat $R/ab.jsonl
cd /tmp/src && source tools/device/env.sh && timeout 200 python -m pytest -p no:warnings -m cuda -o addopts="" -q tests/ops/test_batchnorm.py tests/models 2>&1 | tail -2
