"""Motion blur of forward motion as PSFs: the radial streak a point draws during the exposure .

A vehicle moving forward at speed v sees a static point at depth Z and image distance r from the focus of expansion
(the image centre for a forward-looking camera) move outward at r v / Z pixels per unit time, so over an exposure t
it draws a radial streak of length r v t / Z. With one depth for the scene this is h * s * t at normalised field
height h (1 at the frame corner), s the corner's image speed: the streak grows with the exposure time and with the
distance from the focus of expansion. The streak is centred on the point's position at mid-exposure, so it blurs
without shifting the image.
"""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F


def streak_size(max_length: float) -> int:
    """The odd kernel size that holds a centred streak of ``max_length`` pixels and its bilinear footprint."""
    return 2 * math.ceil(max_length / 2) + 3


def streak_psfs(lengths: torch.Tensor, azimuth: torch.Tensor, size: int, samples: int | None = None) -> torch.Tensor:
    """[N, K, K] uniform line PSFs, each summing to 1: the segment of length ``lengths[n]`` pixels through the
    kernel centre along the direction ``azimuth[n]`` (radians, atan2(y, x) in image rows and columns), rendered as
    ``samples`` points spread bilinearly over pixels (differentiable in the length)."""
    samples = samples or max(16, 4 * size)
    centre = size // 2
    steps = (torch.arange(samples, dtype=lengths.dtype, device=lengths.device) + 0.5) / samples - 0.5  # (-0.5, 0.5)
    along = lengths[:, None] * steps[None, :]  # [N, S]
    x = centre + along * torch.cos(azimuth)[:, None].to(lengths.dtype)
    y = centre + along * torch.sin(azimuth)[:, None].to(lengths.dtype)
    pixels = torch.arange(size, dtype=lengths.dtype, device=lengths.device)
    weight_x = F.relu(1 - (pixels[None, None, :] - x[..., None]).abs())  # [N, S, K]
    weight_y = F.relu(1 - (pixels[None, None, :] - y[..., None]).abs())
    return torch.einsum("nsy,nsx->nyx", weight_y, weight_x) / samples


def compose(psf: torch.Tensor, blur: torch.Tensor) -> torch.Tensor:
    """Convolve each node's PSF [C, Gy, Gx, K, K] with that node's blur [Gy, Gx, L, L] (both odd, centred): the PSF
    of both, [C, Gy, Gx, K + L - 1, K + L - 1] (the full support, nothing cut)."""
    channels, grid_y, grid_x, size, _ = psf.shape
    blur_size = blur.shape[-1]
    nodes = grid_y * grid_x
    images = psf.reshape(channels, nodes, size, size).permute(1, 0, 2, 3).reshape(1, nodes * channels, size, size)
    # conv2d correlates: flip the blur to convolve
    weight = blur.reshape(nodes, 1, 1, blur_size, blur_size).flip(-1, -2).expand(nodes, channels, 1, blur_size,
                                                                                 blur_size)
    out = F.conv2d(images, weight.reshape(nodes * channels, 1, blur_size, blur_size).to(psf.dtype),
                   padding=blur_size - 1, groups=nodes * channels)
    full = out.shape[-1]
    return out.reshape(nodes, channels, full, full).permute(1, 0, 2, 3).reshape(channels, grid_y, grid_x, full, full)
