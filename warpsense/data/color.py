"""sRGB <-> linear radiance (the sRGB transfer function, IEC 61966-2-1)."""

from __future__ import annotations

import torch


def srgb_to_linear(image: torch.Tensor) -> torch.Tensor:
    """Inverse sRGB transfer function (IEC 61966-2-1); input in [0, 1] (uint8 is divided by 255 first)."""
    if image.dtype == torch.uint8:
        image = image.float() / 255.0
    return torch.where(image <= 0.04045, image / 12.92, ((image.clamp_min(0.04045) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(image: torch.Tensor) -> torch.Tensor:
    image = image.clamp(0, 1)
    return torch.where(image <= 0.0031308, image * 12.92, 1.055 * image.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


def to_radiance(image: torch.Tensor) -> torch.Tensor:
    """A frame as linear radiance: uint8 sRGB decoded (`srgb_to_linear`); a float tensor is radiance already."""
    return srgb_to_linear(image) if image.dtype == torch.uint8 else image
