"""Batch normalisation with batch statistics and the ReLU after it in one op: Warp kernels as the custom op
warpsense::batch_norm_relu and its backward."""

from __future__ import annotations

import torch

from warpsense.kernels import batchnorm as kernels
from warpsense.ops._warp import arithmetic_dtype, element_dtype, kernel_scalar, launch, warp_op
from warpsense.ops._warp import bfloat16_words as _words
from warpsense.ops.arguments import check_channel_pairs, check_same_device, check_tensor

# threads per launch on CUDA: the fastest of 2^16, 2^17 and 2^18 at UNROLL 4
_THREADS = {"cuda": 2**17}
_CPU_GROUPS = 16  # Warp's CPU backend runs a launch on one thread: few partial sums


def row_groups(rows: int, lanes: int, device: torch.device, cpu_groups: int = _CPU_GROUPS) -> int:
    """Row groups per launch of the kernels that walk rows (here and `warpsense.ops.gate`), each thread one group's
    rows for one of ``lanes`` channel pairs (and images): enough threads to fill the device, each with at least
    2 UNROLL rows, so that the partial sums, one per group, stay small against the data; ``cpu_groups`` on a CPU."""
    threads = _THREADS.get(device.type)
    groups = threads // lanes if threads else cpu_groups
    return max(1, min(groups, -(-rows // (2 * kernels.UNROLL))))


@warp_op("batch_norm_relu_backward", lambda grad_y, x, stats: (torch.empty_like(x),
                                                                stats.new_empty(2, stats.shape[1])))
def _batch_norm_relu_backward(grad_y: torch.Tensor, x: torch.Tensor,
                              stats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    rows, channels = x.shape
    pairs = channels // 2
    groups = row_groups(rows, pairs, x.device)
    partials = stats.new_empty(groups, 2, channels)
    launch(kernels.gradient_sums, groups * pairs, [_words(grad_y), _words(x), pairs, groups, stats, partials],
           x.device)
    grad_affine = stats.new_empty(2, channels)
    coefficients = stats.new_empty(2, channels)
    launch(kernels.gradient_coefficients, channels, [partials.sum(0), rows, stats, grad_affine, coefficients],
           x.device)
    grad_x = torch.empty_like(x)
    launch(kernels.gradient_input, groups * pairs,
           [_words(grad_y), _words(x), pairs, groups, stats, coefficients, _words(grad_x)], x.device)
    return grad_x, grad_affine


def _setup(ctx, inputs, output):
    ctx.save_for_backward(inputs[0], output[1])
    ctx.mark_non_differentiable(output[1])


def _backward(ctx, grad_y, _grad_stats):
    x, stats = ctx.saved_tensors
    grad_x, grad_affine = _batch_norm_relu_backward(grad_y.to(x.dtype).contiguous(), x, stats)
    return grad_x, grad_affine[0], grad_affine[1], None


def _fake(x, weight, bias, eps):
    return torch.empty_like(x), weight.new_empty(5, x.shape[1])


@warp_op("batch_norm_relu", _fake, _backward, _setup)
def _batch_norm_relu(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor,
                     eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    rows, channels = x.shape
    pairs = channels // 2
    groups = row_groups(rows, pairs, x.device)
    data = _words(x)
    partials = weight.new_empty(groups, 2, channels)
    launch(kernels.batch_sums, groups * pairs, [data, pairs, groups, partials], x.device)
    stats = weight.new_empty(5, channels)  # mean, 1 / sqrt(var + eps), a, bias, var
    launch(kernels.batch_statistics, channels,
           [data, partials.sum(0), weight, bias, kernel_scalar(eps, weight.dtype), stats], x.device)
    y = torch.empty_like(x)
    launch(kernels.normalize_relu, groups * pairs, [data, pairs, groups, stats, _words(y)], x.device)
    return y, stats


@warp_op("batch_norm_update_running", lambda stats, rows, momentum, running_mean, running_var: None,
         mutates_args=("running_mean", "running_var"))
def _update_running(stats: torch.Tensor, rows: int, momentum: float, running_mean: torch.Tensor,
                    running_var: torch.Tensor) -> None:
    launch(kernels.update_running, stats.shape[1],
           [stats, rows, kernel_scalar(momentum, stats.dtype), running_mean, running_var], stats.device)


def batch_norm_relu(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, running_mean: torch.Tensor,
                    running_var: torch.Tensor, momentum: float = 0.1, eps: float = 1e-5) -> torch.Tensor:
    """``relu(F.batch_norm(x, running_mean, running_var, weight, bias, training=True, momentum, eps))``,
    deterministic (`kernels/batchnorm.py`): three passes over memory forward (the statistics; normalise + ReLU) and
    five backward (the gradient sums; the input gradient), where torch's batch norm and ReLU take five and eight.
    Equal to the torch expression up to float rounding; the running statistics move the same way (``running_var``
    towards the unbiased variance).

    Args:
        x: [B, C, H, W] activations, C even, B H W > 1.
        weight, bias: [C] affine parameters (gamma, beta).
        running_mean, running_var: [C] running statistics, updated in place; float64 for float64 x, else float32.
        momentum: the running statistics' update rate in [0, 1] (torch's BatchNorm momentum).
        eps: added to the variance, > 0.

    Returns:
        [B, C, H, W] in channels-last memory (a view of [B, H, W, C]) in x's dtype: bfloat16, float32 or float64
        (float16 computes in float32). Arithmetic is float32 (float64 for float64 x). Channels-last x is read in
        place; other layouts are copied to it once.
    """
    op = "batch_norm_relu"
    batch, channels, height, width = check_channel_pairs(op, x)
    if batch * height * width < 2:
        raise ValueError(f"{op}: batch statistics need more than one value per channel, got x {tuple(x.shape)}")
    # momentum None (nn.BatchNorm2d's cumulative average) would fail in the comparison: "'<=' not supported ..."
    for name, value in (("momentum", momentum), ("eps", eps)):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypeError(f"{op}: {name} must be a float, got {type(value).__name__} {value!r}"
                            + (" (torch's cumulative average is not supported)" if value is None else ""))
    if not 0.0 <= momentum <= 1.0 or not eps > 0.0:
        raise ValueError(f"{op}: momentum must be in [0, 1] and eps > 0, got {momentum!r} and {eps!r}")
    dtype = element_dtype(x.dtype)
    accumulator = arithmetic_dtype(dtype)
    for name, tensor in (("weight", weight), ("bias", bias), ("running_mean", running_mean),
                         ("running_var", running_var)):
        check_tensor(op, name, tensor, 1, f"[{channels}] tensor")
        if tensor.shape[0] != channels:
            raise ValueError(f"{op}: {name} must have shape [{channels}] for x {tuple(x.shape)}, got "
                             f"{tuple(tensor.shape)}")
    for name, tensor in (("running_mean", running_mean), ("running_var", running_var)):
        if tensor.dtype != accumulator or not tensor.is_contiguous():
            raise TypeError(f"{op}: {name} must be a contiguous {accumulator} tensor for {dtype} x (it is updated "
                            f"in place), got {tensor.dtype}")
    check_same_device(op, x=x, weight=weight, bias=bias, running_mean=running_mean, running_var=running_var)
    rows = x.to(dtype).permute(0, 2, 3, 1).contiguous().view(-1, channels)  # a view of channels-last memory
    y, stats = _batch_norm_relu(rows, weight.to(accumulator).contiguous(), bias.to(accumulator).contiguous(),
                                float(eps))
    _update_running(stats.detach(), rows.shape[0], float(momentum), running_mean, running_var)
    return y.view(batch, height, width, channels).permute(0, 3, 1, 2)

