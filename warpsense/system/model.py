"""The model users load: camera -> (fixed ISP) -> segmentation network, as one nn.Module (`SensingModel`), and how a
real RAW capture enters it in place of the camera's simulated one (`SensingModel.sense_capture`)."""

from __future__ import annotations

import torch
from torch import nn

from warpsense.camera import Camera
from warpsense.camera.geometry import cfa_flip, cfa_unflip
from warpsense.camera.isp import FixedISP
from warpsense.data.color import linear_to_srgb, to_radiance

CAPTURE_MEAN_SHARE = 0.5
"""The mean a real RAW capture is scaled to (`SensingModel.sense_capture`), as a share of the mean level the camera
gives in training (`Camera.raw_mean`: the normalised irradiance's mean times the exposure gain). A share of 1 would
match that level; at 0.5 a capture enters the network at about half of it. The value is a convention, not a
measurement (no labelled raw captures judged it): a change moves every prediction of a real capture (`warpsense
predict`), so measure it before changing it."""


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

    def sense_capture(self, mosaic: torch.Tensor) -> torch.Tensor:
        """A real RAW capture as the network's input, in place of the camera's simulated capture.

        Args:
            mosaic: [h, w] normalised mosaic (black 0, white 1) in the CFA phase of this camera's layout
                (`warpsense.data.raw.prepare_capture`).

        Returns:
            [1, 1, h, w] on the model's device (through the fixed ISP where the model has one: [1, 3, h, w]):
            where the camera has an exposure gain, scaled to `CAPTURE_MEAN_SHARE` of the camera's training level
            (`Camera.raw_mean`); clipped to [0, 1]; times a photon budget's digital gain (the capture is in ADC
            units, as the camera's ADC gives them).
        """
        learned = self.camera.learned()
        if learned.exposure_gain is not None:
            mosaic = mosaic * (self.camera.raw_mean() * CAPTURE_MEAN_SHARE / max(float(mosaic.mean()), 1e-6))
        mosaic = mosaic.clamp(0, 1)
        if learned.digital_gain is not None:
            mosaic = mosaic * learned.digital_gain
        sensed = mosaic[None, None].to(next(self.network.parameters()).device)
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
