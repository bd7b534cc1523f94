"""Spatially varying PSF convolution op (Warp kernels in torch autograd) and its alternative methods."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from warpsense.kernels import psf as kernels
from warpsense.ops._warp import launch, prepare, reduction_lanes

PSF_METHODS = ("direct", "fft", "patch")


def _support_bounds(size: int, nodes: int, device) -> torch.Tensor:
    """[nodes, 2] first/last pixel (inclusive, conservative) whose bilinear weight for each node can be nonzero."""
    bounds = []
    for node in range(nodes):
        if nodes == 1:
            bounds.append((0, size - 1))
            continue
        first = 0 if node == 0 else max(0, math.floor((node - 1 + 0.5) * size / nodes - 0.5) - 1)
        last = size - 1 if node == nodes - 1 else min(size - 1, math.ceil((node + 1 + 0.5) * size / nodes - 0.5) + 1)
        bounds.append((first, last))
    return torch.tensor(bounds, dtype=torch.int32, device=device)


class PSFConv(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
        batch, channels, height, width = image.shape
        planes = image.view(batch * channels, height, width)
        out = torch.empty_like(planes)
        nodes = psf.view(channels, psf.shape[1] * psf.shape[2], psf.shape[3], psf.shape[4])
        launch(kernels.psf_forward, (batch * channels, height, width), [planes, nodes, psf.shape[2], out],
               image.device)
        ctx.save_for_backward(image, psf)
        return out.view(batch, channels, height, width)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        image, psf = ctx.saved_tensors
        batch, channels, height, width = image.shape
        _, grid_y, grid_x, size, _ = psf.shape
        grad_planes = grad_out.to(image.dtype).contiguous().view(batch * channels, height, width)
        planes = image.view(batch * channels, height, width)
        grad_image = grad_psf = None
        if ctx.needs_input_grad[0]:
            grad_image = torch.empty_like(planes)
            nodes = psf.view(channels, grid_y * grid_x, size, size)
            launch(kernels.psf_backward_image, (batch * channels, height, width),
                   [grad_planes, nodes, grid_x, grad_image], image.device)
            grad_image = grad_image.view_as(image)
        if ctx.needs_input_grad[1]:
            taps = channels * grid_y * grid_x * size * size
            # enough lanes to fill the device: split each image's output rows into chunks
            target_lanes = max(1, reduction_lanes(1 << 30, image.device) * 8 // max(taps, 1))
            chunks = max(1, min(height, -(-target_lanes // batch)))
            row_chunk = -(-height // chunks)
            chunks = -(-height // row_chunk)
            partials = image.new_empty(taps, batch * chunks)
            launch(
                kernels.psf_backward_psf,
                (taps, batch * chunks),
                [planes, grad_planes, _support_bounds(height, grid_y, image.device),
                 _support_bounds(width, grid_x, image.device), grid_y, grid_x, size, channels, row_chunk, partials],
                image.device,
            )
            grad_psf = partials.sum(dim=1).view_as(psf)
        return grad_image, grad_psf


def _check(image: torch.Tensor, psf: torch.Tensor) -> None:
    if image.dim() != 4:
        raise ValueError(f"psf_conv: image must be [B, C, H, W], got {tuple(image.shape)}")
    if psf.dim() != 5 or psf.shape[3] != psf.shape[4] or psf.shape[3] % 2 == 0:
        raise ValueError(f"psf_conv: psf must be [C, Gy, Gx, K, K] with K odd, got {tuple(psf.shape)}")
    if psf.shape[0] != image.shape[1]:
        raise ValueError(f"psf_conv: psf has {psf.shape[0]} channels, image has {image.shape[1]}")


def psf_conv(image: torch.Tensor, psf: torch.Tensor, method: str = "direct") -> torch.Tensor:
    """Convolve with a spatially varying PSF (paper eq. 2, SPEC section 1).

    Args:
        image: [B, C, H, W] linear irradiance.
        psf: [C, Gy, Gx, K, K] node PSFs (K odd), node (i, j) at the centre of tile (i, j) of a Gy x Gx tiling of
            the image; bilinear in between, clamped beyond the outer centres. Each PSF should sum to 1.
        method: "direct" (exact, Warp kernel; default), "fft" (torch.fft, exact for Gy = Gx = 1 only; with a grid it
            uses the mean PSF) or "patch" (each tile convolved with its own node PSF, no blending: seams).

    Returns:
        [B, C, H, W]. A point source at pixel q renders as PSF_q centred at q (not flipped); borders clamp to edge.
        Differentiable w.r.t. image and psf for every method.
    """
    _check(image, psf)
    if method == "direct":
        image, psf = prepare(image, psf)
        return PSFConv.apply(image, psf)
    if method == "fft":
        return psf_conv_fft(image, psf.mean(dim=(1, 2)))
    if method == "patch":
        return psf_conv_patch(image, psf)
    raise ValueError(f"psf_conv: method must be one of {PSF_METHODS}, got {method!r}")


def psf_conv_fft(image: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Spatially invariant convolution with kernel [C, K, K] by torch.fft on the edge-padded image (exact)."""
    radius = kernel.shape[-1] // 2
    batch, channels, height, width = image.shape
    padded = F.pad(image, (radius,) * 4, mode="replicate")
    full_h, full_w = height + 2 * radius, width + 2 * radius
    spectrum = torch.fft.rfft2(padded, s=(full_h, full_w))
    kernel_spectrum = torch.fft.rfft2(kernel.to(image.dtype), s=(full_h, full_w))
    result = torch.fft.irfft2(spectrum * kernel_spectrum, s=(full_h, full_w))
    # circular convolution of the padded image with the kernel anchored at (0, 0): valid part starts at 2r
    return result[..., 2 * radius : 2 * radius + height, 2 * radius : 2 * radius + width]


def psf_conv_patch(image: torch.Tensor, psf: torch.Tensor) -> torch.Tensor:
    """Patch-wise approximation: each of the Gy x Gx tiles convolved with its own node PSF (cuDNN), no blending."""
    batch, channels, height, width = image.shape
    _, grid_y, grid_x, size, _ = psf.shape
    radius = size // 2
    padded = F.pad(image, (radius,) * 4, mode="replicate")
    row_edges = [round(k * height / grid_y) for k in range(grid_y + 1)]
    col_edges = [round(k * width / grid_x) for k in range(grid_x + 1)]
    pieces = []
    for gy in range(grid_y):
        row = []
        for gx in range(grid_x):
            y0, y1, x0, x1 = row_edges[gy], row_edges[gy + 1], col_edges[gx], col_edges[gx + 1]
            window = padded[..., y0 : y1 + 2 * radius, x0 : x1 + 2 * radius]
            kernel = psf[:, gy, gx].flip(-1, -2).unsqueeze(1).to(image.dtype)
            row.append(F.conv2d(window, kernel, groups=channels))
        pieces.append(torch.cat(row, dim=-1))
    return torch.cat(pieces, dim=-2)
