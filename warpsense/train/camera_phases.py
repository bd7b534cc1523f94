"""Training-time control of the camera: the warm-up / joint phase switch (paper Alg. 1)."""

from __future__ import annotations

from torch import nn

from warpsense.models.sensing import SensingModel


def camera_parameters(model: SensingModel) -> list[nn.Parameter]:
    """The camera parameters the config made learnable (`Camera.learnable_parameters`), frozen or not."""
    return model.camera.learnable_parameters()


def set_camera_trainable(model: SensingModel, trainable: bool) -> None:
    """Phase switch: freeze (warm-up) or unfreeze (joint) every learnable camera parameter; the others stay fixed."""
    for parameter in model.camera.learnable_parameters():
        parameter.requires_grad_(trainable)
    if model.camera.optics is not None:
        model.camera.optics.invalidate_cache()
