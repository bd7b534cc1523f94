#!/usr/bin/env bash
# Multi-GPU scaling on a machine of several GPUs: a study's cells on one GPU against all, and torchrun training on
# one rank against all (tools/device/README.md: the kit installed, .device/camvid carried).
#   bash tools/device/scale.sh study 0      camvid_scaling on GPU 0 alone -> .device/state/scale_1gpu
#   bash tools/device/scale.sh study auto   camvid_scaling over every GPU  -> .device/state/scale_all
#   bash tools/device/scale.sh warm         an untimed warm-up for the two above (every cell for 2 epochs in one
#                                           process, ~80 s: Warp's kernel cache and the bytecode cache filled, so
#                                           that neither side pays them) -> .device/state/scale_warm
#   bash tools/device/scale.sh studies      warm, study 0 and study auto in one call (10-epoch cells fit; the
#                                           plan's 20-epoch cells take ~80 + 330 + 180 s: warm and study 0 in
#                                           one call, study auto in the next)
#   bash tools/device/scale.sh ddp [EPOCHS] torchrun camvid_codesign with the same global batch (data.batch_size is
#                                           global), EPOCHS (default 30): on 1 GPU and on all with the step
#                                           captured as one CUDA graph (the preset; with DDP the all-reduce is
#                                           captured too), then on all GPUs eager -> .device/state/ddp{1,N,N_eager}
#   bash tools/device/scale.sh seeds EPOCHS S.. the final val over seeds, 1 rank against all ranks with the graph:
#                                           the 1-rank runs at once, one per GPU (CUDA_VISIBLE_DEVICES), the
#                                           all-rank runs one after another -> .device/state/seeds{1,N}_sS;
#                                           SIDES=all runs the all-rank side only (SIDES=1: the 1-rank side)
# Each torchrun is stopped after $LIMIT s (default 300: a rank that hangs at exit must not eat the call).
# Extra overrides for the study runs go in $SET (e.g. SET="--set run.deterministic=true" for the per-cell equality
# check, which the throughput figures should not carry: it costs 31% of the step, docs/records/history.md).
# Cells per hour and the GPUs' busy fraction are in each study's throughput.json; everything comes back as
# $OUT/scale.tgz (no plots, no weights).
set -u
what=$1; arg=${2:-}
source tools/device/env.sh
nvidia-smi -L
gpus=$(nvidia-smi -L | wc -l)
mkdir -p .device/state
case $what in
  warm|studies)
    started=$(date +%s)
    # shellcheck disable=SC2086  # $SET first: its own kernels (run.deterministic) are warmed too
    python -m warpsense study run docs/records/plans/camvid_scaling.toml --out .device/state/scale_warm --gpus 0 --per-gpu 1 \
      --set data.root=.device/camvid ${SET:-} --set train.epochs=2 --set train.warmup_epochs=1 > "$OUT/scale_warm.log" 2>&1
    echo "warm-up (untimed by the studies): exit $?, $(( $(date +%s) - started )) s"
    [ "$what" = studies ] && sides="0 auto" || sides=""
    ;;&
  study) sides=$arg ;;&
  warm|study|studies)
    for side in $sides; do
      name=scale_$([ "$side" = auto ] && echo all || echo 1gpu)
      # shellcheck disable=SC2086  # $SET is a list of arguments
      python -m warpsense study run docs/records/plans/camvid_scaling.toml --out ".device/state/$name" --gpus "$side" --per-gpu 1 \
        --set data.root=.device/camvid ${SET:-} > "$OUT/$name.log" 2>&1
      python -m warpsense study report ".device/state/$name" --json "$OUT/$name.json" > "$OUT/$name.txt"
      grep -E "^\[|^study" "$OUT/$name.log" | tail -3; cat ".device/state/$name/throughput.json"
    done
    ;;
  ddp)
    epochs=${arg:-30}
    for run in "1 true" "$gpus true" "$gpus false"; do
      read -r nproc graph <<< "$run"
      name=ddp$nproc$([ "$graph" = false ] && echo _eager)
      timeout "${LIMIT:-300}" torchrun --standalone --nproc_per_node "$nproc" -m warpsense train --config camvid_codesign --no-progress \
        --set train.cuda_graph="$graph" --set data.root=.device/camvid --set run.output_dir=.device/state/$name \
        --set train.epochs="$epochs" --set train.warmup_epochs=$(( epochs * 3 / 10 )) > "$OUT/$name.log" 2>&1
      echo "torchrun N=$nproc cuda_graph=$graph exit $?"; tail -3 "$OUT/$name.log"
    done
    ;;
  seeds)
    epochs=$arg; shift 2
    run() {  # run NPROC SEED: torchrun camvid_codesign with the graph, EPOCHS epochs, seed SEED
      local name=seeds$1_s$2
      timeout "${LIMIT:-300}" torchrun --standalone --nproc_per_node "$1" -m warpsense train --config camvid_codesign --no-progress \
        --set data.root=.device/camvid --set run.output_dir=.device/state/$name --set run.seed="$2" \
        --set train.epochs="$epochs" --set train.warmup_epochs=$(( epochs * 3 / 10 )) > "$OUT/$name.log" 2>&1
      echo "torchrun N=$1 seed=$2 exit $?"; tail -2 "$OUT/$name.log"
    }
    i=0
    case " ${SIDES:-1 all} " in *" 1 "*)
      for seed in "$@"; do  # 1 rank: one run per GPU at once (their img/s are not the scaling figure)
        CUDA_VISIBLE_DEVICES=$(( i % gpus )) run 1 "$seed" &
        i=$(( i + 1 )); [ $(( i % gpus )) = 0 ] && wait
      done
      wait ;;
    esac
    case " ${SIDES:-1 all} " in *" all "*) for seed in "$@"; do run "$gpus" "$seed"; done ;; esac
    ;;
  *) echo "usage: scale.sh study 0|auto | warm | studies | ddp [EPOCHS] | seeds EPOCHS SEED..." >&2; exit 2 ;;
esac
tar czf "$OUT/scale.tgz" --exclude="*.png" --exclude="*.safetensors" -C .device/state .
