"""Building the system from a config or a checkpoint: the composition root of camera, ISP and network."""

from __future__ import annotations

from pathlib import Path

import torch

from warpsense.camera import Camera
from warpsense.camera.isp import FixedISP
from warpsense.config import ConfigError, config_from_dict
from warpsense.models import build_model
from warpsense.system.checkpoint import CheckpointError, read_checkpoint, restore
from warpsense.system.model import SensingModel


def check_config(config, source: str = "config") -> None:
    """The checks that need the implementations (each camera stage's `Stage.check_section`), as one-line
    `ConfigError`s; `warpsense.config` checks types, ranges and choices itself."""
    try:
        Camera.check_config(config, source)
    except ValueError as error:
        raise ConfigError(str(error)) from None


def build_system(config, num_classes: int) -> SensingModel:
    """Camera -> (fixed ISP on the camera's exported layout) -> network, from a resolved config."""
    camera = Camera.from_config(config)
    isp = None
    if config.isp.enabled:
        letters = camera.layout_letters()
        if letters is None:
            raise ValueError("isp.enabled needs a CFA (cfa.enabled = true)")
        isp = FixedISP(letters, config.isp.gamma)
    network = build_model(config.model.name, in_channels=3 if isp is not None else 1,
                          num_classes=config.model.num_classes or num_classes, width=config.model.width,
                          tile=camera.tile, channels_last=config.model.channels_last)
    return SensingModel(camera, network, isp, unprocess_input=config.data.unprocess)


def load_system(checkpoint: str | Path, device) -> tuple[torch.nn.Module, object, dict]:
    """(model in eval mode, config, training state) from a checkpoint written by `warpsense train`."""
    tensors, meta = read_checkpoint(checkpoint)
    config = config_from_dict(meta["config"], source=f"{checkpoint} config")
    check_config(config, f"{checkpoint} config")
    num_classes = meta["state"].get("num_classes")
    if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 1:
        raise CheckpointError(f"{checkpoint}: state.num_classes must be a positive int, got {num_classes!r}")
    model = build_system(config, num_classes)
    restore(tensors, model, source=checkpoint)
    return model.to(device).eval(), config, meta["state"]
