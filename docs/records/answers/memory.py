"""GPU memory of one training process of the presets' recipe (batch 16 at 352 x 480, CUDA graph), then its evaluation
of full 360 x 480 frames at the same batch: torch's peak reserved and nvidia-smi's count for this process.

    python docs/records/answers/memory.py BATCH HEIGHT WIDTH   (alone.sh ran 16 352 480 and 32 352 480)
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "step"))
from step_profile import recipe_step  # noqa: E402


def smi():
    out = subprocess.run(["nvidia-smi", "--query-compute-apps=pid,used_memory", "--format=csv,noheader,nounits"],
                         capture_output=True, text=True).stdout
    return {int(p): float(m) for p, m in (line.split(",") for line in out.strip().splitlines())}.get(os.getpid())

batch, height, width = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
model, step, images, labels = recipe_step(batch, height, width, cuda_graph=True)
for i in range(12):
    step(model, images, labels, i, joint=i >= 6)
torch.cuda.synchronize()
train = {"reserved_gib": torch.cuda.max_memory_reserved() / 2**30, "smi_gib": (smi() or 0) / 1024}
model.eval()
with torch.no_grad():
    for _ in range(3):
        model(torch.rand(batch, 3, 360, 480, device="cuda"), amp=True)
torch.cuda.synchronize()
print(json.dumps({"batch": batch, "crop": [height, width], "train": train,
                  "with_eval": {"reserved_gib": torch.cuda.max_memory_reserved() / 2**30, "smi_gib": (smi() or 0) / 1024}}))
