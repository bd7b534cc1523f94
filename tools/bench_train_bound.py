"""How fast the training step could be without the camera: the same step (`TrainingStep`, the config's compile and
CUDA-graph settings) for the network alone with cross-entropy, the network alone with the config's losses, and the
whole system (camera + network + losses), in one run (issue 11: an upper bound for the training throughput).

    python tools/bench_train_bound.py [--config camvid_codesign] [--set KEY=VALUE ...] [--device cuda]
        [--size 352x480] [--batch 16] [--steps 60] [--variants ce,loss,step] [--json OUT] [--profile DIR]

Inputs are random uint8 images and labels of the given size (the training crop); every step is a joint-phase
step (camera parameters learn). Throughput is images per second over ``--steps`` steps after 8 warm-up steps
(compilation and graph capture happen there). One JSON record per variant is printed; ``--json`` writes them with
the device and versions; ``--variants`` picks some of the three (``ce``: the network alone with cross-entropy,
``loss``: the network alone with the config's losses, ``step``: camera + network + losses), e.g. only ``step`` for a
compiled step, whose compilation takes minutes per variant. ``--profile DIR`` also runs 10 more steps of each variant under `torch.profiler` and
writes the GPU kernels by total time to DIR/profile_<n>.txt (n: the variant's number, from 1).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import torch

from warpsense.bench import parse_size

CROSS_ENTROPY_ONLY = ["loss.ohem_weight=1", "loss.ohem_fraction=1", "loss.lovasz_weight=0", "loss.smooth_weight=0"]
# name -> (label, overrides, network only)
VARIANTS = {"ce": ("network only, cross-entropy", CROSS_ENTROPY_ONLY, True),
            "loss": ("network only, the config's losses", [], True),
            "step": ("camera + network, the config's losses", [], False)}
WARM_UP_STEPS = 8


def step_rate(config, device: torch.device, size: tuple[int, int], batch: int, steps: int, network_only: bool,
              profile: str | None = None) -> float:
    """Images per second of joint-phase training steps; with ``profile``, the kernel table of 10 more steps
    written there."""
    from warpsense.bench.train_suite import step_throughput
    from warpsense.system import SensingModel, build_system
    from warpsense.train.schedule import Schedule
    from warpsense.train.step import TrainingStep

    class NetworkOnly(SensingModel):
        def sense(self, image, image_index=None):  # the mosaic a camera would give, at no cost: the first channel
            return image[:, :1].float() * (1 / 255)

    torch.compiler.reset()
    torch.manual_seed(0)
    model = build_system(config, 11)
    if network_only:
        model = NetworkOnly(model.camera, model.network)
    model = model.to(device).train()
    model.camera.on_epoch(Schedule(2, 1), int(True))  # epoch 1 of 2 is joint
    camera = [] if network_only else model.camera.learnable_parameters()
    camera_ids = {id(p) for p in camera}
    optimizer = torch.optim.AdamW([
        {"params": [p for p in model.parameters() if id(p) not in camera_ids], "lr": config.train.lr},
        {"params": camera, "lr": config.train.lr}], fused=device.type == "cuda")
    amp = config.train.amp and device.type == "cuda"
    step = TrainingStep(config.loss, optimizer, camera, 10_000, amp, config.train.camera_grad_clip,
                        config.train.compile, config.train.cuda_graph)
    rate = step_throughput(step, model, batch, *size, steps, WARM_UP_STEPS, device)
    if profile:
        from warpsense.bench.timing import write_kernel_table

        write_kernel_table(lambda: step_throughput(step, model, batch, *size, 10, 0, device), device, profile,
                           warmup=0)
    return rate


def main(argv: list[str] | None = None) -> int:
    from warpsense.config import ConfigError, load_config
    from warpsense.files import environment

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="camvid_codesign", help="preset name or TOML file")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", choices=("cpu", "cuda"))
    parser.add_argument("--size", default="352x480", help="HxW of the training crop")
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}")
    parser.add_argument("--json", metavar="OUT")
    parser.add_argument("--profile", metavar="DIR", help="write each variant's GPU kernels by time to DIR")
    args = parser.parse_args(argv)
    try:
        height, width = parse_size(args.size, "--size", "352x480")
    except ValueError as error:
        parser.error(str(error))
    names = [name.strip() for name in args.variants.split(",") if name.strip()]
    unknown = [name for name in names if name not in VARIANTS]
    if unknown or not names:
        parser.error(f"--variants: unknown {', '.join(unknown) or 'empty list'}; valid: {', '.join(VARIANTS)}")
    records = []
    if args.profile:
        os.makedirs(args.profile, exist_ok=True)
    for name in names:
        label, overrides, network_only = VARIANTS[name]
        number = list(VARIANTS).index(name) + 1
        try:
            config = load_config(args.config, args.set + overrides)
        except ConfigError as error:
            print(f"bench_train_bound: {error}", file=sys.stderr)
            return 2
        profile = os.path.join(args.profile, f"profile_{number}.txt") if args.profile else None
        rate = step_rate(config, torch.device(args.device), (height, width), args.batch, args.steps, network_only,
                         profile)
        records.append({"variant": label, "config": args.config, "overrides": args.set + overrides,
                        "size": [height, width], "batch": args.batch, "images_per_s": round(rate, 1)})
        print(json.dumps(records[-1]), flush=True)
    if args.json:
        device_name = torch.cuda.get_device_name() if args.device == "cuda" else "cpu"
        with open(args.json, "w") as out:
            json.dump({"device": device_name, "environment": environment(), "records": records}, out, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
