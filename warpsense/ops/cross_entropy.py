"""Softmax and per-pixel cross-entropy of logits in one pass: Warp kernels as the custom op
warpsense::softmax_cross_entropy and its backward (`kernels/cross_entropy.py`)."""

from __future__ import annotations

import torch

from warpsense.kernels import cross_entropy as kernels
from warpsense.ops._warp import arithmetic_dtype, element_dtype, launch, warp_op
from warpsense.ops.arguments import check_class_maps, check_ignore_index


def _backward_fake(probabilities, labels, weights, ignore_index, grad_probabilities, grad_losses, dtype):
    return torch.empty_like(probabilities, dtype=dtype)


@warp_op("softmax_cross_entropy_backward", _backward_fake)
def _softmax_cross_entropy_backward(probabilities: torch.Tensor, labels: torch.Tensor, weights: torch.Tensor,
                                    ignore_index: int, grad_probabilities: torch.Tensor, grad_losses: torch.Tensor,
                                    dtype: torch.dtype) -> torch.Tensor:
    grad_logits = torch.empty_like(probabilities, dtype=dtype)
    batch, _, height, width = probabilities.shape
    launch(kernels.softmax_cross_entropy_backward, (batch, height, width),
           [probabilities, labels, weights, ignore_index, grad_probabilities.to(probabilities.dtype),
            grad_losses.to(probabilities.dtype), grad_logits], probabilities.device)
    return grad_logits


def _setup(ctx, inputs, output):
    logits, labels, weights, ignore_index = inputs
    ctx.save_for_backward(labels, weights, output[1])
    ctx.ignore_index, ctx.dtype = ignore_index, logits.dtype


def _backward(ctx, grad_losses, grad_probabilities):
    labels, weights, probabilities = ctx.saved_tensors
    grad_logits = _softmax_cross_entropy_backward(probabilities, labels, weights, ctx.ignore_index,
                                                  grad_probabilities, grad_losses, ctx.dtype)
    return grad_logits, None, None, None


def _fake(logits, labels, weights, ignore_index):
    arithmetic = arithmetic_dtype(logits.dtype)
    return labels.new_empty(labels.shape, dtype=arithmetic), torch.empty_like(logits, dtype=arithmetic)


@warp_op("softmax_cross_entropy", _fake, _backward, _setup)
def _softmax_cross_entropy(logits: torch.Tensor, labels: torch.Tensor, weights: torch.Tensor,
                           ignore_index: int) -> tuple[torch.Tensor, torch.Tensor]:
    arithmetic = arithmetic_dtype(logits.dtype)
    losses = labels.new_empty(labels.shape, dtype=arithmetic)
    probabilities = torch.empty_like(logits, dtype=arithmetic)
    batch, _, height, width = logits.shape
    launch(kernels.softmax_cross_entropy_forward, (batch, height, width),
           [logits, labels, weights, ignore_index, probabilities, losses], logits.device)
    return losses, probabilities


def softmax_cross_entropy(logits: torch.Tensor, labels: torch.Tensor, weights: torch.Tensor | None = None,
                          ignore_index: int = 255) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel cross-entropy and the class probabilities of logits, one pass forward and one backward
    (`kernels/cross_entropy.py`): ``F.cross_entropy(logits.float(), labels, weight=weights,
    ignore_index=ignore_index, reduction="none")`` and ``torch.softmax(logits.float(), dim=1)``, equal up to float
    rounding, deterministic. Gradients flow into the logits from both outputs.

    Args:
        logits: [B, K, H, W] bfloat16, float32 or float64 (float16 computes in float32), any strides (channels-last
            is read in place; the probabilities and the logits' gradient take the logits' memory format).
        labels: [B, H, W] integer class indices; ``ignore_index`` (and any value outside [0, K)) gives loss 0.
        weights: [K] per-class weights of the losses; None: 1.

    Returns:
        losses [B, H, W] and probabilities [B, K, H, W], float32 (float64 for float64 logits).
    """
    op = "softmax_cross_entropy"
    classes = check_class_maps(op, "logits", logits, labels)[1]
    logits = logits.to(element_dtype(logits.dtype))
    arithmetic = arithmetic_dtype(logits.dtype)
    ignore_index = check_ignore_index(op, ignore_index)
    if weights is None:
        weights = torch.ones(classes, dtype=arithmetic, device=logits.device)
    elif not isinstance(weights, torch.Tensor):
        raise TypeError(f"{op}: weights must be a [K] tensor or None, got {type(weights).__name__} (torch.as_tensor "
                        "converts lists)")
    elif tuple(weights.shape) != (classes,):
        raise ValueError(f"{op}: weights must be [K] = [{classes}], got {tuple(weights.shape)}")
    return _softmax_cross_entropy(logits, labels.to(torch.int32), weights.to(device=logits.device, dtype=arithmetic),
                                  ignore_index)
