#!/bin/bash
# The presets' training step on one GPU (docs/benchmarks.md, "Where the step's time goes"): torch.profiler's kernel
# table over 10 steps, then Nsight Compute's SpeedOfLight section of one step's kernels (NVTX range "prof").
# On the GPU machine after the kit's install (tools/device/README.md), from the repository root.
source tools/device/env.sh
CUDA_VISIBLE_DEVICES=0 timeout 120 python docs/records/step/step_profile.py torch $OUT/step_kernels.json
CUDA_VISIBLE_DEVICES=0 timeout 200 ncu --clock-control none --nvtx --nvtx-include "prof/" --section SpeedOfLight \
  --csv python docs/records/step/step_profile.py ncu - > $OUT/ncu_step.csv 2> $OUT/ncu_step.err
