"""A UNet decoder's bilinear x2 upsampling and skip concatenation in one pass: Warp kernels as the custom op
warpsense::upsample_concat and its backward."""

from __future__ import annotations

import torch

from warpsense.kernels import upsample as kernels
from warpsense.ops._warp import element_dtype, launch, warp_op
from warpsense.ops.arguments import check_same_device, check_tensor


def _threads(count: int) -> int:
    """The kernels' one-dimensional launch size; their index arithmetic is 32-bit."""
    if count >= 2**31:
        raise ValueError(f"upsample_concat: {count} threads exceed the kernels' 32-bit indexing; split the batch")
    return count


@warp_op("upsample_concat_backward", lambda grad_out, channels: grad_out.new_empty(
    grad_out.shape[0], grad_out.shape[1] // 2, grad_out.shape[2] // 2, channels))
def _upsample_concat_backward(grad_out: torch.Tensor, channels: int) -> torch.Tensor:
    batch, height, width = grad_out.shape[0], grad_out.shape[1] // 2, grad_out.shape[2] // 2
    grad_x = grad_out.new_empty(batch, height, width, channels)
    groups = -(-width // kernels.RUN)
    launch(kernels.upsample_concat_backward, _threads(batch * height * groups * channels), [grad_out, groups, grad_x],
           grad_out.device)
    return grad_x


def _backward(ctx, grad_out):
    channels = ctx.channels
    grad_out = grad_out.contiguous()
    # the skip's gradient as a view: a skip feeds an encoder stage too, so autograd sums the two gradients and that
    # sum reads the view in place of a copy
    return _upsample_concat_backward(grad_out, channels), grad_out[..., channels:]


def _setup(ctx, inputs, output):
    ctx.channels = inputs[0].shape[3]


def _fake(x, skip):
    return x.new_empty(skip.shape[0], skip.shape[1], skip.shape[2], x.shape[3] + skip.shape[3])


@warp_op("upsample_concat", _fake, _backward, _setup)
def _upsample_concat(x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
    batch, height, width = skip.shape[:3]
    out = x.new_empty(batch, height, width, x.shape[3] + skip.shape[3])
    groups = -(-width // kernels.RUN)
    launch(kernels.upsample_concat_forward, _threads(batch * height * groups * x.shape[3]), [x, groups, out], x.device)
    out[..., x.shape[3]:].copy_(skip)
    return out


def upsample_concat(x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
    """``torch.cat([F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False), skip], dim=1)`` in one
    pass forward and one backward, deterministic (`kernels/upsample.py`): a UNet decoder's upsampling and skip
    connection. Equal to the torch expression up to float rounding.

    Args:
        x: [B, C1, h, w] features to upsample.
        skip: [B, C2, 2h, 2w] features to append, same device.

    Returns:
        [B, C1 + C2, 2h, 2w] in channels-last memory (a view of [B, 2h, 2w, C1 + C2]), in the inputs' promoted
        dtype: bfloat16, float32 or float64 (float16 inputs compute in float32). Channels-last inputs are read in
        place; others are copied to that layout once.
    """
    op = "upsample_concat"
    check_tensor(op, "x", x, 4, "[B, C1, h, w] tensor")
    check_tensor(op, "skip", skip, 4, "[B, C2, 2h, 2w] tensor")
    check_same_device(op, x=x, skip=skip)
    batch, _, height, width = x.shape
    if skip.shape[0] != batch or tuple(skip.shape[2:]) != (2 * height, 2 * width):
        raise ValueError(f"{op}: skip must be [B, C2, 2h, 2w] = [{batch}, C2, {2 * height}, {2 * width}] for x "
                         f"{tuple(x.shape)}, got {tuple(skip.shape)}")
    dtype = element_dtype(torch.promote_types(x.dtype, skip.dtype))
    # [B, H, W, C] with the channels innermost: views of channels-last memory, copies of any other
    x_last = x.to(dtype).permute(0, 2, 3, 1).contiguous()
    skip_last = skip.to(dtype).permute(0, 2, 3, 1).contiguous()
    return _upsample_concat(x_last, skip_last).permute(0, 3, 1, 2)
