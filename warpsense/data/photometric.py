"""Photometric augmentation of the scene's linear radiance before the camera (training only).

A camera co-designed on a few drives sees their light, colour and lens fall-off only. Drawing these per training
image, on the radiance that enters the simulated lens, exposes the network and the camera to scenes the training
drives did not show, while the camera itself (its noise, CFA and ADC) stays the deployment camera. Evaluation never
jitters: the deployment point is fixed.
"""

from __future__ import annotations

import math

import torch
from torch import nn

JITTER_KEYS = ("jitter_stops", "jitter_gamma", "jitter_white_balance", "jitter_vignetting")
"""The [data] keys of `RadianceJitter`, in its arguments' order."""


class RadianceJitter(nn.Module):
    """Random exposure, contrast (gamma), white balance and vignetting of linear radiance [B, 3, H, W], drawn per
    image from torch's generator on the radiance's device (a captured CUDA graph draws anew on every replay).

    Args:
        stops: exposure: radiance x 2^u, u uniform in [-stops, stops] (0 = off).
        gamma: contrast: radiance^g with ln g uniform in [-ln(1 + gamma), ln(1 + gamma)] (0 = off); radiance is in
            [0, 1] here (decoded sRGB), so the white point stays.
        white_balance: colour temperature and tint: the red and blue channels x e^v, v uniform in
            [-white_balance, white_balance] each, green fixed (0 = off).
        vignetting: lens fall-off: radiance x (1 - a r^2), r the distance from the crop's centre over the half
            diagonal (1 in the corners), a uniform in [0, vignetting] (0 = off; at most 1).

    The order is the scene's (contrast, colour), then the lens's (vignetting), then the exposure's.
    """

    def __init__(self, stops: float = 0.0, gamma: float = 0.0, white_balance: float = 0.0, vignetting: float = 0.0):
        super().__init__()
        for name, value, high in (("stops", stops, 16.0), ("gamma", gamma, 10.0),
                                  ("white_balance", white_balance, 2.0), ("vignetting", vignetting, 1.0)):
            if not 0 <= value <= high:
                raise ValueError(f"data.jitter_{name} must be in [0, {high:g}], got {value}")
        self.stops, self.gamma, self.white_balance, self.vignetting = stops, gamma, white_balance, vignetting

    @classmethod
    def from_config(cls, data) -> "RadianceJitter | None":
        """From the [data] section's ``jitter_*`` keys; None when all are 0 (no augmentation, no cost)."""
        values = [getattr(data, key) for key in JITTER_KEYS]
        return cls(*values) if any(values) else None

    def forward(self, radiance: torch.Tensor) -> torch.Tensor:
        if radiance.dim() != 4 or radiance.shape[1] != 3:
            raise ValueError(f"radiance jitter takes linear radiance [B, 3, H, W], got {tuple(radiance.shape)}")
        batch, _, height, width = radiance.shape
        draws = torch.rand(batch, 5, device=radiance.device) * 2 - 1  # uniform in [-1, 1]
        image = radiance.clamp_min(0)
        if self.gamma:
            exponent = torch.exp(draws[:, 0] * math.log1p(self.gamma))
            image = image.clamp_max(1) ** exponent.view(batch, 1, 1, 1)
        if self.white_balance:
            red_blue = torch.exp(draws[:, 1:3] * self.white_balance)
            gains = torch.stack([red_blue[:, 0], torch.ones_like(red_blue[:, 0]), red_blue[:, 1]], dim=1)
            image = image * gains.view(batch, 3, 1, 1)
        if self.vignetting:
            rows = torch.linspace(-1, 1, height, device=image.device).view(height, 1) * (height / 2)
            cols = torch.linspace(-1, 1, width, device=image.device).view(1, width) * (width / 2)
            radius2 = (rows**2 + cols**2) / ((height / 2) ** 2 + (width / 2) ** 2)
            strength = (draws[:, 3] + 1) * (self.vignetting / 2)
            image = image * (1 - strength.view(batch, 1, 1, 1) * radius2)
        if self.stops:
            image = image * torch.exp2(draws[:, 4] * self.stops).view(batch, 1, 1, 1)
        return image
