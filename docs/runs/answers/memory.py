"""GPU memory of one training process of the presets' recipe (batch 16 at 352 x 480, CUDA graph), then its evaluation
of full 360 x 480 frames at the same batch: torch's peak reserved and nvidia-smi's count for this process.

    python docs/runs/answers/memory.py BATCH HEIGHT WIDTH   (alone.sh ran 16 352 480 and 32 352 480)
"""
import json
import os
import subprocess
import sys

import torch

from warpsense.camera.camera import set_finite_check
from warpsense.config import load_config
from warpsense.data.photometric import RadianceJitter
from warpsense.system.build import build_system
from warpsense.train.engine import _optimizer
from warpsense.train.step import TrainingStep


def smi():
    out = subprocess.run(["nvidia-smi", "--query-compute-apps=pid,used_memory", "--format=csv,noheader,nounits"],
                         capture_output=True, text=True).stdout
    return {int(p): float(m) for p, m in (line.split(",") for line in out.strip().splitlines())}.get(os.getpid())

batch, height, width = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
torch.manual_seed(0)
config = load_config("camvid_codesign", [])
model = build_system(config, 11).cuda().train()
set_finite_check(model, False)
optimizer = _optimizer(config, model, torch.device("cuda"))
step = TrainingStep(config.loss, optimizer, model.camera.learnable_parameters(), 1000, True,
                    config.train.camera_grad_clip, "off", True, radiance_jitter=RadianceJitter.from_config(config.data))
images = torch.randint(0, 256, (batch, 3, height, width), dtype=torch.uint8, device="cuda")
labels = torch.randint(0, 11, (batch, height, width), device="cuda")
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
