"""Lovasz-softmax loss of class probabilities from one sort of all classes' errors: Warp kernels around a torch
sort, as the custom op warpsense::lovasz_softmax_terms (`kernels/lovasz.py`)."""

from __future__ import annotations

import math

import torch

from warpsense.kernels import lovasz as kernels
from warpsense.ops._warp import launch, warp_op
from warpsense.ops.arguments import check_class_maps, check_ignore_index

TILE = {"cuda": 256, "cpu": 32}
"""Sorted keys per block of the counting and gradient kernels, by device type (a tile is one block)."""
MAX_CLASSES = 64
"""The keys are 31 bits: the class, 2 flags and the error's level (29 - class bits; 23 at 64 classes)."""


def level_bits(classes: int) -> int:
    """Bits of an error's level in the sort keys of ``classes`` classes (`kernels/lovasz.py`)."""
    return 29 - max(1, math.ceil(math.log2(classes)))


def _terms_fake(probabilities, labels, ignore_index):
    classes = probabilities.shape[1]
    return (probabilities.new_empty(classes), labels.new_empty(classes, dtype=torch.int32),
            probabilities.new_empty(probabilities.shape))


def _terms_setup(ctx, inputs, output):
    ctx.save_for_backward(output[2])
    ctx.mark_non_differentiable(output[1], output[2])
    ctx.set_materialize_grads(False)  # no zero-filled gradients for the outputs that do not take one


def _terms_backward(ctx, grad_losses, grad_foreground, grad_gradient):
    if grad_losses is None:
        return None, None, None
    (gradient,) = ctx.saved_tensors
    return gradient * grad_losses.to(gradient.dtype).view(1, -1, 1, 1), None, None


@warp_op("lovasz_softmax_terms", _terms_fake, _terms_backward, _terms_setup)
def _lovasz_terms(probabilities: torch.Tensor, labels: torch.Tensor,
                  ignore_index: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each class's Lovasz loss [K], foreground pixel count [K] (int32) and d loss_c / d p_c [B, K, H, W]
    contiguous (the backward's factor; not differentiable)."""
    batch, classes, height, width = probabilities.shape
    device = probabilities.device
    tile = TILE["cuda" if device.type == "cuda" else "cpu"]
    padded = -(-batch * height * width // tile) * tile  # each class's keys in whole tiles
    tiles = classes * padded // tile
    bits = level_bits(classes)
    keys = torch.empty(classes * padded, dtype=torch.int32, device=device)
    launch(kernels.lovasz_keys, padded, [probabilities, labels, ignore_index, bits, keys], device)
    keys, order = torch.sort(keys, stable=True)
    counts = torch.empty(tiles, dtype=torch.int32, device=device)
    launch(kernels.lovasz_counts, tiles, [keys, counts], device, block_dim=tile)
    running = counts.view(classes, -1).cumsum(1, dtype=torch.int32)
    foreground = running[:, -1].contiguous()
    # class planes (NCHW) whatever the probabilities' layout: each class's scattered writes then stay within one
    # plane, which the L2 cache holds (10.8 MB at the recipe's batch); channels-last, they would spread over the
    # whole tensor and miss the cache
    gradient = torch.empty(probabilities.shape, dtype=probabilities.dtype, device=device)
    sums = probabilities.new_empty(tiles)
    launch(kernels.lovasz_gradient, tiles,
           [keys, order, (running - counts.view(classes, -1)).view(-1), foreground, bits, gradient, sums], device,
           block_dim=tile)
    # sum over a class's pixels of d (p - fg) = e g: sum d p - sum_fg d
    losses = (gradient * probabilities).sum(dim=(0, 2, 3)) - sums.view(classes, -1).sum(1)
    return losses, foreground, gradient


def lovasz_softmax(probabilities: torch.Tensor, labels: torch.Tensor, ignore_index: int = 255) -> torch.Tensor:
    """Lovasz-softmax loss (Berman, Rannen Triki, Blaschko, CVPR 2018, alg. 1) averaged over the classes present in
    ``labels``, every class from one sort (`kernels/lovasz.py`). Errors closer than 2^-(29 - class bits) (3e-8
    at 11 classes) may be ranked in either order, which moves a class's loss by at most that much; otherwise it
    equals `warpsense.ops.reference.lovasz_softmax_reference`. Deterministic.

    Args:
        probabilities: [B, K, H, W] class probabilities in [0, 1], K <= `MAX_CLASSES`, any strides (a
            channels-last or strided view is read in place); float32 or float64 (half types are computed in
            float32). Gradients flow into it.
        labels: [B, H, W] integer class indices; ``ignore_index`` marks pixels that count for no class.

    Returns:
        0-d tensor in the kernels' dtype; 0 when no pixel is labelled.
    """
    op = "lovasz_softmax"
    batch, classes, height, width = check_class_maps(op, "probabilities", probabilities, labels)
    if classes > MAX_CLASSES:
        raise ValueError(f"{op}: at most {MAX_CLASSES} classes (31-bit sort keys), got {classes}")
    if classes * (batch * height * width + TILE["cuda"]) >= 2**31:
        raise ValueError(f"{op}: classes x pixels must be < 2^31 (int32 indices), got {classes} x "
                         f"{batch * height * width}")
    if probabilities.dtype not in (torch.float32, torch.float64):
        probabilities = probabilities.float()
    losses, foreground, _ = _lovasz_terms(probabilities, labels.to(torch.int32),
                                           check_ignore_index(op, ignore_index))
    present = (foreground > 0).to(losses.dtype)
    return (losses * present).sum() / present.sum().clamp_min(1)
