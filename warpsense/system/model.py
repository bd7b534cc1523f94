"""The model users load: camera -> (fixed ISP) -> segmentation network, as one nn.Module (`SensingModel`)."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from warpsense.camera import Camera
from warpsense.camera.isp import FixedISP
from warpsense.data.color import linear_to_srgb, srgb_to_linear


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
        return srgb_to_linear(image) if image.dtype == torch.uint8 else image

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


def cfa_flip(sensed: torch.Tensor, tile: int) -> tuple[torch.Tensor, int]:
    """Mirror a capture [B, C, H, W] left-right so that every pixel keeps its CFA site.

    A plain flip moves column x to W - 1 - x, whose site differs when W is even (2x2 tiles); shifting the mirrored
    frame by ``shift`` = (W - 1) mod 2 columns (edge column repeated) restores the phase. Tiles wider than 2 have no
    such shift. Returns (mirrored capture, shift) for `cfa_unflip`."""
    if tile > 2:
        raise ValueError(f"flip test-time augmentation keeps the CFA phase only for 1x1 and 2x2 tiles, got {tile}x{tile}")
    width = sensed.shape[-1]
    shift = (width - 1) % 2 if tile == 2 else 0
    mirrored = sensed.flip(-1)
    if shift:
        mirrored = F.pad(mirrored, (shift, 0, 0, 0), mode="replicate")[..., :width]
    return mirrored, shift


def cfa_unflip(prediction: torch.Tensor, shift: int) -> torch.Tensor:
    """Map a prediction on `cfa_flip`'s capture back to the original columns (the ``shift`` edge columns it cannot
    see repeat their neighbour)."""
    restored = prediction[..., shift:].flip(-1)
    return F.pad(restored, (shift, 0, 0, 0), mode="replicate") if shift else restored
