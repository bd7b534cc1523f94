#!/usr/bin/env bash
# Long GPU work that outlives a call (the device tool's calls last at most 10 minutes; a process started with setsid
# outlives its call until the machine goes back): start a script in the background, then poll it from later calls,
# each poll bringing back everything so far (no weights, no plots) as $OUT/background.tgz, so that a machine taken
# back early still leaves the finished cells here.
# Usage (from the repository root on the GPU machine, after the kit's install):
#   bash tools/device/background.sh start SCRIPT [ARGS...]   # runs `bash SCRIPT ARGS` with setsid, log in /tmp/bg
#   bash tools/device/background.sh poll SECONDS DIR...      # waits up to SECONDS (or until SCRIPT ends), then tars
#                                                            # /tmp/bg and each DIR into $OUT/background.tgz
# SCRIPT runs from the repository root with tools/device/env.sh sourced; a study in it writes under /tmp (e.g.
# `warpsense study run PLAN --out /tmp/studies/NAME --gpus auto --per-gpu 3 --mps on --set data.root=...`).
set -u
mode=$1; shift
mkdir -p /tmp/bg
case $mode in
  start)
    script=$1; shift
    [ -f /tmp/bg/running ] && { echo "background.sh: a script is running already ($(cat /tmp/bg/running))"; exit 2; }
    echo "$script $*" > /tmp/bg/running
    rm -f /tmp/bg/rc /tmp/bg/end
    setsid nohup bash -c "source tools/device/env.sh; export PYTHONUNBUFFERED=1; date +%s > /tmp/bg/start;
      bash $script $*; echo \$? > /tmp/bg/rc; date +%s > /tmp/bg/end; rm -f /tmp/bg/running" \
      > /tmp/bg/log 2>&1 < /dev/null &
    sleep 5; tail -5 /tmp/bg/log ;;
  poll)
    seconds=$1; shift
    waited=0
    while [ -f /tmp/bg/running ] && [ "$waited" -lt "$seconds" ]; do sleep 10; waited=$((waited + 10)); done
    tar czf "$OUT/background.tgz" --exclude='*.safetensors' --exclude='*.png' /tmp/bg "$@" 2>/dev/null
    tail -4 /tmp/bg/log
    for dir in "$@"; do
      echo "$dir: $(find "$dir" -name evaluation.json 2>/dev/null | wc -l) cells evaluated"
    done
    if [ -f /tmp/bg/rc ]; then echo "finished: exit $(cat /tmp/bg/rc) after $(( $(cat /tmp/bg/end) - $(cat /tmp/bg/start) )) s"
    else echo "running for $(( $(date +%s) - $(cat /tmp/bg/start) )) s"; fi ;;
  *)
    echo "usage: background.sh start SCRIPT [ARGS...] | poll SECONDS DIR..."; exit 2 ;;
esac
