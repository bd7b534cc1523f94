#!/bin/bash
# Nsight Compute profile of the PSF convolution's kernels (forward, PSF adjoint) at the camera's training shape.
cd /tmp/src && source tools/device/env.sh
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
ncu --clock-control none --kernel-name regex:psf --launch-skip 2 --launch-count 2 --section SpeedOfLight \
  --section Occupancy --section LaunchStats --section ComputeWorkloadAnalysis --section WarpStateStats \
  --section MemoryWorkloadAnalysis --section InstructionStats python /tmp/p.py > $OUT/ncu_psf.txt 2>&1
echo "ncu exit $?"
grep -E "psf_|Duration|Compute \(SM\) Throughput|Memory Throughput|Achieved Occupancy|Theoretical Occupancy|Registers Per|Issue Slots Busy|Executed Ipc|No Eligible|L1/TEX Hit|Block Limit" $OUT/ncu_psf.txt | head -60
