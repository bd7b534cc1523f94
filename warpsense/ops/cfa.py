"""CFA mosaic op: Warp kernel registered into torch autograd."""

from __future__ import annotations

import torch

from warpsense.kernels import cfa as kernels
from warpsense.ops._warp import launch, prepare, reduction_lanes


def site_reduction_buffers(rgb: torch.Tensor, tile: int, want_rgb: bool, sums: int):
    """Outputs of a per-site backward kernel (thread = (CFA site, lane)): grad_rgb (a 1-element stand-in when it is
    not wanted) and partials [T * T, lanes, sums], with enough lanes to fill the device."""
    batch, _, height, width = rgb.shape
    lanes = reduction_lanes(batch * (-(-height // tile)) * (-(-width // tile)), rgb.device)
    grad_rgb = torch.empty_like(rgb) if want_rgb else rgb.new_empty(1, 3, 1, 1)
    return grad_rgb, rgb.new_empty(tile * tile, lanes, sums)


class CFAMosaic(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rgb: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
        batch, _, height, width = rgb.shape
        raw = rgb.new_empty(batch, 1, height, width)
        launch(kernels.cfa_forward, (batch, height, width), [rgb, phi, raw], rgb.device)
        ctx.save_for_backward(rgb, phi)
        return raw

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_raw: torch.Tensor):
        rgb, phi = ctx.saved_tensors
        grad_raw = grad_raw.to(rgb.dtype).contiguous()
        tile = phi.shape[0]
        want_rgb = ctx.needs_input_grad[0]
        grad_rgb, partials = site_reduction_buffers(rgb, tile, want_rgb, 3)
        launch(kernels.cfa_backward, tuple(partials.shape[:2]), [rgb, phi, grad_raw, int(want_rgb), grad_rgb, partials],
               rgb.device)
        grad_phi = partials.sum(dim=1).reshape(tile, tile, 3) if ctx.needs_input_grad[1] else None
        return (grad_rgb if want_rgb else None), grad_phi


def cfa_mosaic(rgb: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Mosaic a linear RGB image through a colour filter array (paper eq. 4).

    Args:
        rgb: [B, 3, H, W] linear irradiance (any real values; >= 0 physically).
        phi: [T, T, 3] spectral response of each CFA site; pixel (y, x) uses phi[y % T, x % T].

    Returns:
        raw: [B, 1, H, W], raw(p) = sum_c rgb[c](p) * phi[p mod T, c]. Differentiable w.r.t. rgb and phi.
        float16/bfloat16 inputs compute in float32. NaN/Inf in the inputs propagate to the affected pixels.
    """
    if rgb.dim() != 4 or rgb.shape[1] != 3:
        raise ValueError(f"cfa_mosaic: rgb must be [B, 3, H, W], got {tuple(rgb.shape)}")
    if phi.dim() != 3 or phi.shape[0] != phi.shape[1] or phi.shape[2] != 3 or phi.shape[0] < 1:
        raise ValueError(f"cfa_mosaic: phi must be [T, T, 3] with T >= 1, got {tuple(phi.shape)}")
    rgb, phi = prepare(rgb, phi)
    return CFAMosaic.apply(rgb, phi)
