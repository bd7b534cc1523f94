"""The model users load: camera -> (fixed ISP) -> segmentation network, as one nn.Module (`SensingModel`)."""

from __future__ import annotations

import torch
from torch import nn

from warpsense.camera import Camera
from warpsense.camera.geometry import cfa_flip, cfa_unflip
from warpsense.camera.isp import FixedISP
from warpsense.data.color import linear_to_srgb, to_radiance


class SensingModel(nn.Module):
    """uint8 sRGB or linear radiance [B, 3, H, W] -> (logits [B, K, H, W], sensor output fed to the network).

    ``srgb_input``: the network reads the clean sRGB frame in [0, 1] instead of a capture (no camera: the RGB
    teacher of distillation, model.input = "srgb"; linear radiance is encoded back to sRGB)."""

    def __init__(self, camera: Camera, network: nn.Module, isp: FixedISP | None = None, srgb_input: bool = False):
        super().__init__()
        self.camera = camera
        self.isp = isp
        self.network = network
        self.srgb_input = srgb_input

    def radiance(self, image: torch.Tensor) -> torch.Tensor:
        """uint8 sRGB -> linear radiance (float tensors are taken as radiance already)."""
        return to_radiance(image)

    def sense(self, image: torch.Tensor, image_index: torch.Tensor | None = None) -> torch.Tensor:
        if self.srgb_input:
            return image.float() * (1 / 255) if image.dtype == torch.uint8 else linear_to_srgb(image)
        sensed = self.camera(self.radiance(image), image_index)
        return self.isp(sensed) if self.isp is not None else sensed

    def forward(self, image: torch.Tensor, amp: bool = False, image_index: torch.Tensor | None = None):
        """``image_index`` [B]: the images' indices in their dataset, which key the eval-mode sensor noise."""
        sensed = self.sense(image, image_index)
        with torch.autocast(device_type=sensed.device.type, dtype=torch.bfloat16, enabled=amp):
            logits = self.network(sensed)
        return logits, sensed

    @torch.no_grad()
    def probabilities(self, image: torch.Tensor, amp: bool = False, image_index: torch.Tensor | None = None,
                      flip: bool = False) -> torch.Tensor:
        """Class probabilities [B, K, H, W] of one capture; ``flip``: averaged with those of the horizontally
        mirrored capture (`cfa_flip`, the CFA phase kept: test-time augmentation on that capture, no second
        exposure)."""
        logits, sensed = self(image, amp, image_index)
        probabilities = torch.softmax(logits.float(), dim=1)
        if not flip:
            return probabilities
        mirrored, shift = cfa_flip(sensed, self.camera.tile if self.isp is None else 1)
        flipped = cfa_unflip(self._network(mirrored, amp).float(), shift)
        return (probabilities + torch.softmax(flipped, dim=1)) / 2

    def _network(self, sensed: torch.Tensor, amp: bool) -> torch.Tensor:
        with torch.autocast(device_type=sensed.device.type, dtype=torch.bfloat16, enabled=amp):
            return self.network(sensed)
