"""sRGB -> linear radiance, and the "unprocessing" of Brooks et al. (CVPR 2019, "Unprocessing Images for Learned
Raw Denoising", section 3)."""

from __future__ import annotations

import torch

# sRGB -> XYZ (D65) and XYZ -> camera of a typical smartphone sensor; Brooks et al. draw random CCMs, we use one
# fixed, representative matrix so runs are reproducible.
_XYZ_FROM_SRGB = torch.tensor([[0.4124564, 0.3575761, 0.1804375],
                               [0.2126729, 0.7151522, 0.0721750],
                               [0.0193339, 0.1191920, 0.9503041]])
_CAMERA_FROM_XYZ = torch.tensor([[1.0234, -0.2969, -0.2266],
                                 [-0.5625, 1.6328, -0.0469],
                                 [-0.0703, 0.2188, 0.6406]])


def srgb_to_linear(image: torch.Tensor) -> torch.Tensor:
    """Inverse sRGB transfer function (IEC 61966-2-1); input in [0, 1] (uint8 is divided by 255 first)."""
    if image.dtype == torch.uint8:
        image = image.float() / 255.0
    return torch.where(image <= 0.04045, image / 12.92, ((image.clamp_min(0.04045) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(image: torch.Tensor) -> torch.Tensor:
    image = image.clamp(0, 1)
    return torch.where(image <= 0.0031308, image * 12.92, 1.055 * image.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


def unprocess(linear_rgb: torch.Tensor, red_gain: float = 1.9, blue_gain: float = 1.6) -> torch.Tensor:
    """Linear sRGB [B, 3, H, W] -> camera-space radiance: inverse colour correction (sRGB -> camera, rows
    normalised to sum 1) then inverse white balance (divide R and B by their gains), clipped at 0."""
    camera_from_srgb = _CAMERA_FROM_XYZ @ _XYZ_FROM_SRGB
    camera_from_srgb = camera_from_srgb / camera_from_srgb.sum(dim=1, keepdim=True)
    camera = torch.einsum("ij,bjhw->bihw", camera_from_srgb.to(linear_rgb), linear_rgb)
    gains = torch.tensor([1.0 / red_gain, 1.0, 1.0 / blue_gain]).to(linear_rgb).view(1, 3, 1, 1)
    return (camera * gains).clamp_min(0)
