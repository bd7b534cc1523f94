# The step's img/s (docs/records/step/concurrency/concurrency.py's `timed`) of cfcdea8 (`git archive` as
# .device/src_old.tar.gz) against the work tree (252e0d5's change), twice in alternation, on one GPU after the kit's
# install (tools/device/README.md) -> $OUT/ab.jsonl; then trace.py's log of one step's large ops -> $OUT/trace.txt
set -u
R=$OUT; mkdir -p /tmp/src_old && tar xzf .device/src_old.tar.gz -C /tmp/src_old
cat > /tmp/abstep.py <<'PY'
import json, sys
from pathlib import Path
sys.path.insert(0, str(Path("docs/records/step/concurrency").resolve()))
import concurrency
print(json.dumps({"tree": sys.argv[1], "step_images_per_s": concurrency.timed(1, concurrency.BATCH, 60, 8)}), flush=True)
PY
NEW=$PWD
for round in 1 2; do
  for tree in /tmp/src_old $NEW; do
    (cd $tree && source tools/device/env.sh && python /tmp/abstep.py $tree 2>/dev/null | tail -1) >> $R/ab.jsonl
  done
done
cat $R/ab.jsonl
source tools/device/env.sh
timeout 120 python docs/records/step/copies/trace.py > $R/trace.txt 2>&1; echo trace $?
