"""CFA mosaic op: Warp kernels as the custom ops warpsense::cfa_mosaic and its backward."""

from __future__ import annotations

import torch

from warpsense.kernels import cfa as kernels
from warpsense.ops._warp import launch, prepare, reduction_lanes, save_inputs, warp_op
from warpsense.ops.arguments import check_same_device, check_tensor


def site_reduction_buffers(rgb: torch.Tensor, tile: int, want_rgb: bool, sums: int):
    """Outputs of a per-site backward kernel (thread = (CFA site, lane)): grad_rgb (a 1-element stand-in when it is
    not wanted) and partials [T * T, lanes, sums], with enough lanes to fill the device."""
    batch, _, height, width = rgb.shape
    lanes = reduction_lanes(batch * (-(-height // tile)) * (-(-width // tile)), rgb.device)
    return rgb_gradient_buffer(rgb, want_rgb), rgb.new_empty(tile * tile, lanes, sums)


def rgb_gradient_buffer(rgb: torch.Tensor, want_rgb: bool) -> torch.Tensor:
    """grad_rgb of a per-site backward kernel: rgb's shape, or a 1-element stand-in when it is not wanted (also the
    ops' fake implementation of that output)."""
    return torch.empty_like(rgb) if want_rgb else rgb.new_empty(1, 3, 1, 1)


def _cfa_backward_fake(rgb, phi, grad_raw, want_rgb):
    return rgb_gradient_buffer(rgb, want_rgb), torch.empty_like(phi)


@warp_op("cfa_mosaic_backward", _cfa_backward_fake)
def _cfa_mosaic_backward(rgb: torch.Tensor, phi: torch.Tensor, grad_raw: torch.Tensor,
                         want_rgb: bool) -> tuple[torch.Tensor, torch.Tensor]:
    grad_raw = grad_raw.to(rgb.dtype).contiguous()
    tile = phi.shape[0]
    grad_rgb, partials = site_reduction_buffers(rgb, tile, want_rgb, 3)
    launch(kernels.cfa_backward, tuple(partials.shape[:2]), [rgb, phi, grad_raw, int(want_rgb), grad_rgb, partials],
           rgb.device)
    return grad_rgb, partials.sum(dim=1).reshape(tile, tile, 3)


def _cfa_backward(ctx, grad_raw):
    rgb, phi = ctx.saved_tensors
    grad_rgb, grad_phi = _cfa_mosaic_backward(rgb, phi, grad_raw, ctx.needs_input_grad[0])
    return (grad_rgb if ctx.needs_input_grad[0] else None), (grad_phi if ctx.needs_input_grad[1] else None)


@warp_op("cfa_mosaic", lambda rgb, phi: rgb.new_empty(rgb.shape[0], 1, *rgb.shape[2:]), _cfa_backward, save_inputs)
def _cfa_mosaic(rgb: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    batch, _, height, width = rgb.shape
    raw = rgb.new_empty(batch, 1, height, width)
    launch(kernels.cfa_forward, (batch, height, width), [rgb, phi, raw], rgb.device)
    return raw


def cfa_mosaic(rgb: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Mosaic a linear RGB image through a colour filter array (eq. 4 of the paper, docs/references.md).

    Args:
        rgb: [B, 3, H, W] linear irradiance (any real values; >= 0 physically).
        phi: [T, T, 3] spectral response of each CFA site; pixel (y, x) uses phi[y % T, x % T].

    Returns:
        raw: [B, 1, H, W], raw(p) = sum_c rgb[c](p) * phi[p mod T, c]. Differentiable w.r.t. rgb and phi.
        float16/bfloat16 inputs compute in float32. NaN/Inf in the inputs propagate to the affected pixels.
    """
    check_tensor("cfa_mosaic", "rgb", rgb, 4, "[B, 3, H, W]")
    check_tensor("cfa_mosaic", "phi", phi)
    check_same_device("cfa_mosaic", rgb=rgb, phi=phi)
    if rgb.shape[1] != 3:
        raise ValueError(f"cfa_mosaic: rgb must be [B, 3, H, W], got {tuple(rgb.shape)}")
    if phi.dim() != 3 or phi.shape[0] != phi.shape[1] or phi.shape[2] != 3 or phi.shape[0] < 1:
        raise ValueError(f"cfa_mosaic: phi must be [T, T, 3] with T >= 1, got {tuple(phi.shape)}")
    rgb, phi = prepare(rgb, phi)
    return _cfa_mosaic(rgb, phi)
