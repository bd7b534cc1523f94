#!/bin/bash
# Nsight Compute's L1 tables of the PSF kernels (forward, PSF adjoint) at the camera's training shape: requests,
# wavefronts and sectors of their global loads, and the source counters (docs/benchmarks.md, PSF convolution, what
# bounds the PSF adjoint). On the GPU machine after the kit's install, from the repository root; output in $OUT.
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
ncu --clock-control none --kernel-name regex:psf --launch-skip 2 --launch-count 2 \
  --section MemoryWorkloadAnalysis_Tables --section SourceCounters --section WarpStateStats \
  --metrics l1tex__t_requests_pipe_lsu_mem_global_op_ld.sum,l1tex__t_sectors_pipe_lsu_mem_global_op_ld.sum,l1tex__data_pipe_lsu_wavefronts_mem_lg_cmd_read.sum,l1tex__data_pipe_lsu_wavefronts.sum,l1tex__lsu_writeback_active.avg.pct_of_peak_sustained_elapsed,l1tex__throughput.avg.pct_of_peak_sustained_elapsed,sm__cycles_elapsed.avg \
  python /tmp/p.py > $OUT/ncu_psf_l1.txt 2>&1
echo "ncu exit $?"
grep -E "psf_|l1tex__|sm__cycles|Wavefronts|Excessive|uncoalesced|Global Load" $OUT/ncu_psf_l1.txt | cut -c1-200 | head -60
