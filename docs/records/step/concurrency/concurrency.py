"""Several training runs on one GPU: the ways of issue 55, measured on the recipe's own training step.

    python docs/records/step/concurrency/concurrency.py --json OUT.json [--copies 2,3] [--steps 60]

The step is the camvid_codesign preset's (codesign camera, the recipe's network, full loss, joint phase, bf16,
replayed as one CUDA graph, fused AdamW), batch 16 at the training crop 352 x 480, each copy with its own
parameters, optimizer and graph (as separate cells would have). Modes, each timed after its warm-up (graph capture
included there), total images per second over all copies:

- ``alone``: one copy (the baseline: one cell per GPU).
- ``streams``: N copies in one process, each replaying its graph on its own CUDA stream, queued round-robin by the
  host (issue 55's option b: several cells in one worker on their own streams and graphs).
- ``processes``: N processes of ``alone`` at once under a CUDA MPS daemon started for them (option a, as the study
  pool runs it with ``--mps on``), timed over the same window (a file barrier after each one's warm-up).
- ``batch``: one copy at batch 16 N. Every way of training N seeds as one batched model (option c: vmap over
  stacked parameters, grouped convolutions) streams the same activations per image as this, through kernels no
  larger, and grouped or batched-weight convolutions run no faster per image than a dense batch: its img/s is an
  upper bound of option c's.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from warpsense.bench.train_suite import PRESET, recipe_network
from warpsense.camera import Camera
from warpsense.camera.camera import set_finite_check
from warpsense.config import load_config
from warpsense.study.mps import mps_daemon
from warpsense.system import SensingModel
from warpsense.train.step import TrainingStep

HEIGHT, WIDTH, BATCH = 352, 480, 16


def copy_step(seed: int, batch: int):
    """One run's system, step and a batch of random frames and labels on the GPU."""
    torch.manual_seed(seed)
    system = SensingModel(Camera.from_config(load_config(PRESET)), recipe_network()).cuda().train()
    set_finite_check(system, False)
    parameters = [p for p in system.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(parameters, lr=1e-3, fused=True)
    step = TrainingStep(load_config(PRESET).loss, optimizer, [], 10_000, amp=True, cuda_graph=True)
    images = torch.randint(0, 256, (batch, 3, HEIGHT, WIDTH), dtype=torch.uint8, device="cuda")
    labels = torch.randint(0, 11, (batch, HEIGHT, WIDTH), device="cuda")
    return system, step, images, labels


def timed(copies: int, batch: int, steps: int, warmup: int, barrier: tuple[Path, int] | None = None) -> float:
    """Total img/s of ``copies`` copies stepping round-robin, each on its own stream, over ``steps`` rounds."""
    runs = [copy_step(seed, batch) for seed in range(copies)]
    streams = [torch.cuda.Stream() for _ in runs]

    def round_(index):
        for stream, (system, step, images, labels) in zip(streams, runs):
            with torch.cuda.stream(stream):
                step(system, images, labels, index, joint=True)

    for index in range(warmup):
        round_(index)
    torch.cuda.synchronize()
    if barrier is not None:  # processes: start the timed window together
        folder, count = barrier
        (folder / f"ready{os.getpid()}").touch()
        while len(list(folder.glob("ready*"))) < count:
            time.sleep(0.01)
    start = time.perf_counter()
    for index in range(steps):
        round_(warmup + index)
    torch.cuda.synchronize()
    return steps * batch * copies / (time.perf_counter() - start)


def processes(count: int, steps: int, warmup: int) -> float:
    """Total img/s of ``count`` processes of one copy each, under an MPS daemon, over a common window."""
    with mps_daemon(True) as environment, tempfile.TemporaryDirectory() as folder:
        commands = [[sys.executable, __file__, "--child", folder, str(count), str(steps), str(warmup)]
                    for _ in range(count)]
        children = [subprocess.Popen(command, env={**os.environ, **environment}, stdout=subprocess.PIPE, text=True)
                    for command in commands]
        rates = [float(child.communicate()[0].strip().splitlines()[-1]) for child in children]
    return sum(rates)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", required=False)
    parser.add_argument("--copies", default="2,3")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--warmup", type=int, default=8)
    parser.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        folder, count, steps, warmup = args.child
        print(timed(1, BATCH, int(steps), int(warmup), (Path(folder), int(count))), flush=True)
        return
    records = []

    def add(mode, copies, rate, alone):
        record = {"mode": mode, "copies": copies, "images_per_s": rate, "ratio_to_alone": rate / alone}
        records.append(record)
        print(f"{mode:>9s} x{copies}: {rate:7.1f} img/s total, {rate / alone:.2f}x alone", flush=True)

    alone = timed(1, BATCH, args.steps, args.warmup)
    add("alone", 1, alone, alone)
    for copies in (int(n) for n in args.copies.split(",")):
        add("streams", copies, timed(copies, BATCH, args.steps, args.warmup), alone)
        add("processes", copies, processes(copies, args.steps, args.warmup), alone)
        add("batch", copies, timed(1, BATCH * copies, args.steps, args.warmup), alone)
    alone_again = timed(1, BATCH, args.steps, args.warmup)
    add("alone", 1, alone_again, alone)
    if args.json:
        Path(args.json).write_text(json.dumps({"device": torch.cuda.get_device_name(0), "torch": torch.__version__,
                                               "shape": [BATCH, 3, HEIGHT, WIDTH], "records": records}, indent=1))


if __name__ == "__main__":
    main()
