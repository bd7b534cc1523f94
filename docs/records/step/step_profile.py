"""The presets' training step (camvid_codesign: camera + DSUNet + the recipe's loss, joint phase, bf16 channels-last,
eager) on random frames, on one CUDA GPU. `torch OUT.json`: images/s of 20 eager steps and torch.profiler's kernel
table over 10 steps (microseconds and launches a step). `ncu -`: 8 warm steps, then one step inside the NVTX range
"prof" for Nsight Compute (`profile.sh`)."""

import json
import sys
import time

import torch
from torch.profiler import ProfilerActivity, profile

from warpsense.camera.camera import set_finite_check
from warpsense.config import load_config
from warpsense.data.photometric import RadianceJitter
from warpsense.system.build import build_system
from warpsense.train.engine import _optimizer
from warpsense.train.step import TrainingStep


def recipe_step(batch: int = 16, height: int = 352, width: int = 480, cuda_graph: bool = False):
    """The presets' system (seed 0, on the GPU, training mode), its training step (``cuda_graph``: replayed as one
    graph per phase) and a batch of random frames and labels: (model, step, images, labels). Also used by
    docs/records/step/copies/trace.py and docs/records/answers/memory.py."""
    torch.manual_seed(0)
    config = load_config("camvid_codesign", [])
    model = build_system(config, 11).cuda().train()
    set_finite_check(model, False)  # as in training: no host read per step
    optimizer = _optimizer(config, model, torch.device("cuda"))
    step = TrainingStep(config.loss, optimizer, model.camera.learnable_parameters(), 1000, True,
                        config.train.camera_grad_clip, "off", cuda_graph,
                        radiance_jitter=RadianceJitter.from_config(config.data))
    images = torch.randint(0, 256, (batch, 3, height, width), dtype=torch.uint8, device="cuda")
    labels = torch.randint(0, 11, (batch, height, width), device="cuda")
    return model, step, images, labels


def main(mode: str, out: str) -> None:
    model, step, images, labels = recipe_step()
    for index in range(8):
        step(model, images, labels, index, joint=True)
    torch.cuda.synchronize()
    if mode == "ncu":
        torch.cuda.nvtx.range_push("prof")
        step(model, images, labels, 8, joint=True)
        torch.cuda.synchronize()
        torch.cuda.nvtx.range_pop()
        return
    start = time.perf_counter()
    for index in range(20):
        step(model, images, labels, 8 + index, joint=True)
    torch.cuda.synchronize()
    eager = 20 * 16 / (time.perf_counter() - start)
    with profile(activities=[ProfilerActivity.CUDA]) as profiler:
        for index in range(10):
            step(model, images, labels, 28 + index, joint=True)
        torch.cuda.synchronize()
    rows = sorted(((event.key, event.device_time_total / 10, event.count / 10) for event in profiler.key_averages()),
                  key=lambda row: -row[1])
    with open(out, "w") as file:
        json.dump({"eager_img_per_s": eager, "kernels_us_per_step": rows}, file, indent=1)
    print(f"eager {eager:.1f} img/s; kernels {sum(row[1] for row in rows) / 1000:.2f} ms a step")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
