"""The co-designed system: camera -> (fixed ISP) -> segmentation network, as one nn.Module."""

from __future__ import annotations

import torch
from torch import nn

from warpsense.camera import Camera
from warpsense.camera.isp import FixedISP
from warpsense.camera.cfa import layout_letters
from warpsense.data.color import srgb_to_linear, unprocess
from warpsense.models import build_model


class SensingModel(nn.Module):
    """uint8 sRGB or linear radiance [B, 3, H, W] -> (logits [B, K, H, W], sensor output fed to the network)."""

    def __init__(self, camera: Camera, network: nn.Module, isp: FixedISP | None = None, unprocess_input: bool = False):
        super().__init__()
        self.camera = camera
        self.isp = isp
        self.network = network
        self.unprocess_input = unprocess_input

    def radiance(self, image: torch.Tensor) -> torch.Tensor:
        """uint8 sRGB -> linear radiance (float tensors are taken as radiance already)."""
        if image.dtype == torch.uint8:
            image = srgb_to_linear(image)
            if self.unprocess_input:
                image = unprocess(image)
        return image

    def sense(self, image: torch.Tensor, image_index: torch.Tensor | None = None) -> torch.Tensor:
        sensed = self.camera(self.radiance(image), image_index)
        return self.isp(sensed) if self.isp is not None else sensed

    def forward(self, image: torch.Tensor, amp: bool = False, image_index: torch.Tensor | None = None):
        """``image_index`` [B]: the images' indices in their dataset, which key the eval-mode sensor noise."""
        sensed = self.sense(image, image_index)
        with torch.autocast(device_type=sensed.device.type, dtype=torch.bfloat16, enabled=amp):
            logits = self.network(sensed)
        return logits, sensed


def build_system(config, num_classes: int) -> SensingModel:
    camera = Camera.from_config(config)
    isp = None
    if config.isp.enabled:
        if camera.cfa is None:
            raise ValueError("isp.enabled needs a CFA (cfa.enabled = true)")
        isp = FixedISP(layout_letters(config.cfa.pattern, config.cfa.tile), config.isp.gamma)
    network = build_model(config.model.name, in_channels=3 if isp is not None else 1,
                          num_classes=config.model.num_classes or num_classes, width=config.model.width,
                          tile=camera.tile)
    return SensingModel(camera, network, isp, unprocess_input=config.data.unprocess)


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
