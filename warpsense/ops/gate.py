"""A squeeze-and-excitation gate times channels-last activations, plus an optional residual, in one pass forward
and one backward: Warp kernels as the custom op warpsense::channel_gate and its backward."""

from __future__ import annotations

import torch

from warpsense.kernels import gate as kernels
from warpsense.ops._warp import arithmetic_dtype, element_dtype, launch, warp_op
from warpsense.ops._warp import bfloat16_words as _words
from warpsense.ops.arguments import check_channel_pairs, check_same_device, check_tensor
from warpsense.ops.batchnorm import row_groups

_CPU_GROUPS = 4  # pixel groups per image on the CPU, whose backend runs a launch on one thread


def _groups(batch: int, pixels: int, pairs: int, device: torch.device) -> int:
    """Pixel groups per image (each thread walks one group's pixels of one image for one channel pair)."""
    return row_groups(pixels, batch * pairs, device, _CPU_GROUPS)


@warp_op("channel_gate_backward", lambda grad_out, x, gate: (torch.empty_like(x), torch.empty_like(gate)))
def _channel_gate_backward(grad_out: torch.Tensor, x: torch.Tensor,
                           gate: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    batch, pixels, channels = x.shape
    pairs = channels // 2
    groups = _groups(batch, pixels, pairs, x.device)
    grad_x = torch.empty_like(x)
    partials = gate.new_empty(batch, groups, channels)
    launch(kernels.gate_backward, batch * groups * pairs,
           [_words(grad_out), _words(x), gate, pairs, groups, _words(grad_x), partials], x.device)
    return grad_x, partials.sum(1)


def _setup(ctx, inputs, output):
    x, gate, residual = inputs
    ctx.save_for_backward(x, gate)
    ctx.has_residual = residual is not None


def _backward(ctx, grad_out):
    x, gate = ctx.saved_tensors
    grad_out = grad_out.to(x.dtype).contiguous()
    grad_x, grad_gate = _channel_gate_backward(grad_out, x, gate)
    return grad_x, grad_gate, grad_out if ctx.has_residual else None


@warp_op("channel_gate", lambda x, gate, residual: torch.empty_like(x), _backward, _setup)
def _channel_gate(x: torch.Tensor, gate: torch.Tensor, residual: torch.Tensor | None) -> torch.Tensor:
    batch, pixels, channels = x.shape
    pairs = channels // 2
    groups = _groups(batch, pixels, pairs, x.device)
    out = torch.empty_like(x)
    launch(kernels.gate_forward, batch * groups * pairs,
           [_words(x), gate, _words(x if residual is None else residual), int(residual is not None), pairs, groups,
            _words(out)], x.device)
    return out


def channel_gate(x: torch.Tensor, gate: torch.Tensor, residual: torch.Tensor | None = None) -> torch.Tensor:
    """``x * gate`` (+ ``residual``) for per-image channel gates, in one pass over the pixels forward and one
    backward (`kernels/gate.py`), deterministic: a squeeze-and-excitation block's excitation and its block's
    residual connection. torch's broadcast multiply and add take two passes forward (the multiply at a broadcast
    kernel's speed) and three over a product backward. Equal to the torch expression up to float rounding.

    Args:
        x: [B, C, H, W] activations, C even.
        gate: [B, C, 1, 1] (or [B, C]) gates, any float dtype (computed with in float32, float64 for float64 x).
        residual: optional [B, C, H, W] activations added to the product.

    Returns:
        [B, C, H, W] in channels-last memory (a view of [B, H, W, C]) in x's dtype: bfloat16, float32 or float64
        (float16 computes in float32). Channels-last x and residual are read in place; other layouts are copied to
        it once.
    """
    op = "channel_gate"
    batch, channels, height, width = check_channel_pairs(op, x)
    check_tensor(op, "gate", gate)
    if gate.numel() != batch * channels or gate.shape[:2] != (batch, channels):
        raise ValueError(f"{op}: gate must be [B, C, 1, 1] or [B, C] = [{batch}, {channels}] for x "
                         f"{tuple(x.shape)}, got {tuple(gate.shape)}")
    tensors = {"x": x, "gate": gate}
    if residual is not None:
        check_tensor(op, "residual", residual, 4, "[B, C, H, W] tensor")
        if residual.shape != x.shape:
            raise ValueError(f"{op}: residual must have x's shape {tuple(x.shape)}, got {tuple(residual.shape)}")
        tensors["residual"] = residual
    check_same_device(op, **tensors)
    dtype = element_dtype(x.dtype)

    def pixels(tensor):  # [B, H W, C]: a view of channels-last memory, a copy of any other
        return tensor.to(dtype).permute(0, 2, 3, 1).contiguous().view(batch, height * width, channels)

    out = _channel_gate(pixels(x), gate.reshape(batch, channels).to(arithmetic_dtype(dtype)).contiguous(),
                        None if residual is None else pixels(residual))
    return out.view(batch, height, width, channels).permute(0, 3, 1, 2)
