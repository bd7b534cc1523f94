"""Training-time control of the camera: which of its parameters learn, and the warm-up / joint phase switch."""

from __future__ import annotations

from torch import nn

from warpsense.models.sensing import SensingModel


def camera_parameters(model: SensingModel) -> list[nn.Parameter]:
    """Learnable camera parameters (those constructed as learnable)."""
    return [p for p in model.camera.parameters() if getattr(p, "_learnable", p.requires_grad)]


def mark_learnable(model: SensingModel) -> None:
    """Remember which camera parameters the config made learnable, before phases toggle requires_grad."""
    for p in model.camera.parameters():
        p._learnable = p.requires_grad


def set_camera_trainable(model: SensingModel, trainable: bool) -> None:
    """Phase switch: freeze (warm-up) or unfreeze (joint) every learnable camera parameter."""
    for p in model.camera.parameters():
        p.requires_grad_(trainable and p._learnable)
    if model.camera.optics is not None:
        model.camera.optics.invalidate_cache()
