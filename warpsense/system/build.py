"""Building the system from a config or a checkpoint: the composition root of camera, ISP and network."""

from __future__ import annotations

from pathlib import Path

import torch

from warpsense.camera import Camera
from warpsense.camera.camera import STAGES
from warpsense.camera.isp import FixedISP
from warpsense.choices import DEVICES
from warpsense.config import ConfigError, config_from_dict
from warpsense.models import network_from_config
from warpsense.system.checkpoint import CheckpointError, read_checkpoint, restore
from warpsense.system.device import resolve_device
from warpsense.system.model import SensingModel


def check_config(config, source: str = "config") -> None:
    """The checks that need the implementations (each camera stage's `Stage.check_section`), as one-line
    `ConfigError`s; `warpsense.config` checks types, ranges and choices itself."""
    try:
        Camera.check_config(config, source)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    if config.model.input == "srgb":
        sections = [stage.config_section for stage in STAGES.values()] + ["isp"]
        on = [section for section in sections if getattr(config, section).enabled]
        if on:
            raise ConfigError(f"{source}: model.input = \"srgb\" reads the clean frame without a camera; disable "
                              f"{', '.join(f'{section}.enabled' for section in on)}")
    if config.loss.distill_weight > 0 and not config.loss.teacher:
        raise ConfigError(f"{source}: loss.distill_weight = {config.loss.distill_weight} needs loss.teacher (a "
                          "checkpoint, e.g. of the camvid_rgb_teacher preset)")


def build_system(config, num_classes: int) -> SensingModel:
    """Camera -> (fixed ISP on the camera's exported layout) -> network, from a resolved config; ``num_classes``
    (a positive int) is the network's output count unless ``model.num_classes`` sets it."""
    # 0 would build a head of no outputs (zero-element weights, one torch warning), 11.0 fail inside torch.empty
    if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 1:
        raise ValueError(f"build_system: num_classes must be a positive int, got {num_classes!r}")
    camera = Camera.from_config(config)
    isp = None
    if config.isp.enabled:
        letters = camera.layout_letters()
        if letters is None:
            raise ValueError("isp.enabled needs a CFA (cfa.enabled = true)")
        isp = FixedISP(letters, config.isp.gamma)
    srgb = config.model.input == "srgb"
    network = network_from_config(config.model, 3 if isp is not None or srgb else 1, num_classes, camera.tile)
    return SensingModel(camera, network, isp, srgb_input=srgb)


def load_teacher(checkpoint: str | Path, num_classes: int, device) -> SensingModel:
    """A frozen teacher for distillation (loss.teacher): the checkpoint's model in eval mode, no gradients, checked
    to predict the student's ``num_classes``."""
    teacher, _, _ = load_system(checkpoint, device)
    classes = teacher.network.head.out_channels
    if classes != num_classes:
        raise CheckpointError(f"{checkpoint}: loss.teacher predicts {classes} classes, the dataset has {num_classes}")
    teacher.requires_grad_(False)
    return teacher


def load_system(checkpoint: str | Path, device) -> tuple[torch.nn.Module, object, dict]:
    """(model in eval mode, config, training state) from a checkpoint written by `warpsense train`, on ``device`` (a
    torch.device, or a name: "cpu", "cuda" or "auto"; cuda where torch has none is a one-line ValueError)."""
    if isinstance(device, str) and device in DEVICES:
        device = resolve_device(device)
    elif torch.device(device).type == "cuda":
        resolve_device("cuda")  # torch's own error for a missing CUDA is a bare assertion deep in .to()
    tensors, meta = read_checkpoint(checkpoint)
    config = config_from_dict(meta["config"], source=f"{checkpoint} config")
    check_config(config, f"{checkpoint} config")
    num_classes = meta["state"].get("num_classes")
    if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 1:
        raise CheckpointError(f"{checkpoint}: state.num_classes must be a positive int, got {num_classes!r}")
    names = meta["state"].get("class_names")  # eval and predict name the classes by it
    if names is not None and not (isinstance(names, list) and all(isinstance(name, str) for name in names)):
        raise CheckpointError(f"{checkpoint}: state.class_names must be a list of class names, got {names!r}")
    model = build_system(config, num_classes)
    restore(tensors, model, source=checkpoint)
    return model.to(device).eval(), config, meta["state"]
