"""Lovasz with the row-wise cumsum (before) against the flattened int32 running count (after): loss alone and the
camvid_codesign training step (compiled + whole-step CUDA graph), same call."""
import json
import os
import time

import torch
from torch.utils import benchmark

import warpsense.train.losses as losses
from warpsense.config import load_config
from warpsense.system import build_system
from warpsense.train.schedule import Schedule
from warpsense.train.step import TrainingStep

new_grad = losses.lovasz_grad


@torch.compiler.disable
def old_grad(sorted_labels):
    gts = sorted_labels.sum(dim=-1, keepdim=True)
    intersection = gts - sorted_labels.cumsum(-1)
    union = gts + (1 - sorted_labels).cumsum(-1)
    jaccard = 1.0 - intersection / union
    if jaccard.shape[-1] > 1:
        jaccard = torch.cat([jaccard[..., :1], jaccard[..., 1:] - jaccard[..., :-1]], dim=-1)
    return jaccard


torch.manual_seed(0)
logits0 = torch.randn(16, 11, 352, 480, device="cuda", dtype=torch.bfloat16) * 3
target = torch.randint(0, 11, (16, 352, 480), device="cuda")
records = []
for name, grad in (("before (row-wise cumsum)", old_grad), ("after (flattened int32 count)", new_grad)):
    losses.lovasz_grad = grad
    def run():
        logits = logits0.detach().requires_grad_(True)
        value = losses.lovasz_softmax(logits, target)
        value.backward()
        return value
    ms = benchmark.Timer("run()", globals={"run": run}).blocked_autorange(min_run_time=2).median * 1e3
    records.append({"what": "lovasz forward+backward [16, 11, 352, 480]", "variant": name, "ms": round(ms, 3),
                    "value": float(run())})
    print(json.dumps(records[-1]), flush=True)


def step_rate(steps=60):
    torch.compiler.reset()
    config = load_config("camvid_codesign")
    model = build_system(config, 11).cuda().train()
    model.camera.on_epoch(Schedule(2, 1), int(True))  # epoch 1 of 2 is joint
    camera = model.camera.learnable_parameters()
    ids = {id(p) for p in camera}
    optimizer = torch.optim.AdamW([{"params": [p for p in model.parameters() if id(p) not in ids], "lr": 3e-3},
                                   {"params": camera, "lr": 3e-3}], fused=True)
    step = TrainingStep(config.loss, optimizer, camera, 10_000, True, 1.0, config.train.compile, config.train.cuda_graph)
    images = torch.randint(0, 256, (16, 3, 352, 480), dtype=torch.uint8, device="cuda")
    labels = torch.randint(0, 11, (16, 352, 480), device="cuda")
    for i in range(8):
        step(model, images, labels, i, True)
    torch.cuda.synchronize()
    started = time.perf_counter()
    for i in range(steps):
        step(model, images, labels, 8 + i, True)
    torch.cuda.synchronize()
    return steps * 16 / (time.perf_counter() - started)


for repeat in range(2):
    for name, grad in (("before (row-wise cumsum)", old_grad), ("after (flattened int32 count)", new_grad)):
        losses.lovasz_grad = grad
        rate = step_rate()
        records.append({"what": "camvid_codesign step, batch 16, 352x480, compiled + graph, joint phase",
                        "variant": name, "repeat": repeat, "images_per_s": round(rate, 1)})
        print(json.dumps(records[-1]), flush=True)
json.dump({"device": torch.cuda.get_device_name(), "torch": torch.__version__, "records": records},
          open(os.path.join(os.environ["OUT"], "lovasz_ab.json"), "w"), indent=1)
