#!/bin/bash
# Nsight Compute profile of the PSF convolution's kernels (forward, PSF adjoint) at the camera's training shape.
#   bash docs/records/psf/profile.sh       -> $OUT/ncu_psf.txt: speed of light, occupancy, warp states, instructions
#   bash docs/records/psf/profile.sh l1    -> $OUT/ncu_psf_l1.txt: the L1 tables (requests, wavefronts and sectors of the
#                                          global loads) and the source counters (what bounds the PSF adjoint)
# On the GPU machine after the kit's install, from the repository root (docs/benchmarks.md, PSF convolution).
source tools/device/env.sh
cat > /tmp/p.py <<'PY'
import torch
from warpsense.ops import psf_conv
torch.manual_seed(0)
x = torch.rand(16, 3, 352, 480, device="cuda")
p = torch.rand(3, 5, 5, 15, 15, device="cuda", requires_grad=True)
for _ in range(3):
    psf_conv(x, p, "direct").sum().backward()
torch.cuda.synchronize()
PY
python /tmp/p.py && echo warm-ok
profile() { ncu --clock-control none --kernel-name regex:psf --launch-skip 2 --launch-count 2 "$@" python /tmp/p.py; }
if [ "${1:-}" = l1 ]; then
  profile --section MemoryWorkloadAnalysis_Tables --section SourceCounters --section WarpStateStats \
    --metrics l1tex__t_requests_pipe_lsu_mem_global_op_ld.sum,l1tex__t_sectors_pipe_lsu_mem_global_op_ld.sum,l1tex__data_pipe_lsu_wavefronts_mem_lg_cmd_read.sum,l1tex__data_pipe_lsu_wavefronts.sum,l1tex__lsu_writeback_active.avg.pct_of_peak_sustained_elapsed,l1tex__throughput.avg.pct_of_peak_sustained_elapsed,sm__cycles_elapsed.avg \
    > $OUT/ncu_psf_l1.txt 2>&1
  echo "ncu exit $?"
  grep -E "psf_|l1tex__|sm__cycles|Wavefronts|Excessive|uncoalesced|Global Load" $OUT/ncu_psf_l1.txt | cut -c1-200 | head -60
else
  profile --section SpeedOfLight --section Occupancy --section LaunchStats --section ComputeWorkloadAnalysis \
    --section WarpStateStats --section MemoryWorkloadAnalysis --section InstructionStats > $OUT/ncu_psf.txt 2>&1
  echo "ncu exit $?"
  grep -E "psf_|Duration|Compute \(SM\) Throughput|Memory Throughput|Achieved Occupancy|Theoretical Occupancy|Registers Per|Issue Slots Busy|Executed Ipc|No Eligible|L1/TEX Hit|Block Limit" $OUT/ncu_psf.txt | head -60
fi
