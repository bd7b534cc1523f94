"""Edge-aware smoothness of class probabilities (eq. 9 of the paper): Warp kernels as the custom ops
warpsense::smoothness_map and its backward."""

from __future__ import annotations

import torch

from warpsense.kernels import smoothness as kernels
from warpsense.ops._warp import launch, prepare, save_inputs, scalar_tensor, warp_op
from warpsense.ops.arguments import check_same_device, check_tensor


def _map_backward_fake(probabilities, guide, params, grad_map):
    return torch.empty_like(probabilities), torch.empty_like(guide)


@warp_op("smoothness_map_backward", _map_backward_fake)
def _smoothness_map_backward(probabilities: torch.Tensor, guide: torch.Tensor, params: torch.Tensor,
                             grad_map: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    grad_map = grad_map.to(guide.dtype).contiguous()
    grad_probabilities, grad_guide = torch.empty_like(probabilities), torch.empty_like(guide)
    launch(kernels.smoothness_backward, tuple(guide.shape),
           [probabilities, guide, params, grad_map, grad_probabilities, grad_guide], guide.device)
    return grad_probabilities, grad_guide


def _map_backward(ctx, grad_map):
    probabilities, guide, params = ctx.saved_tensors
    grad_probabilities, grad_guide = _smoothness_map_backward(probabilities, guide, params, grad_map)
    return grad_probabilities, grad_guide, None


@warp_op("smoothness_map", lambda probabilities, guide, params: torch.empty_like(guide), _map_backward, save_inputs)
def _smoothness_map(probabilities: torch.Tensor, guide: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
    out = torch.empty_like(guide)
    launch(kernels.smoothness_forward, tuple(guide.shape), [probabilities, guide, params, out], guide.device)
    return out


def edge_aware_smoothness(probabilities: torch.Tensor, guide: torch.Tensor, sigma: float = 0.1) -> torch.Tensor:
    """Mean over 4-neighbour pairs of w_pq |P(p) - P(q)|_1, w_pq = exp(-|g_p - g_q| / sigma) (eq. 9 of the paper):
    half the mean over horizontal pairs plus half the mean over vertical ones, so predictions stay smooth except
    across the guide's edges. One fused pass forward and one backward (`kernels/smoothness.py`);
    `warpsense.ops.reference.edge_aware_smoothness_reference` is the same formula in plain torch.

    Args:
        probabilities: [B, K, H, W] class probabilities, H, W >= 2 (any memory format: channels-last is read in
            place, others are copied to it once). Gradients flow into it.
        guide: [B, H, W] one-channel guide image (the sensor output), same B, H, W. Gradients flow into it too,
            through the weights.
        sigma: edge scale of the guide, > 0, in the guide's units.

    Returns:
        0-d tensor in the kernels' dtype (float64 if either input is, else float32).
    """
    op = "edge_aware_smoothness"
    check_tensor(op, "probabilities", probabilities, 4, "[B, K, H, W] tensor")
    check_tensor(op, "guide", guide, 3, "[B, H, W] tensor")
    check_same_device(op, probabilities=probabilities, guide=guide)
    batch, _, height, width = probabilities.shape
    if tuple(guide.shape) != (batch, height, width):
        raise ValueError(f"{op}: guide must be [B, H, W] = {(batch, height, width)} to match probabilities "
                         f"{tuple(probabilities.shape)}, got {tuple(guide.shape)}")
    if height < 2 or width < 2:
        raise ValueError(f"{op}: need images of at least 2 x 2 pixels (a mean over pairs both ways), got "
                         f"probabilities {tuple(probabilities.shape)}")
    if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not 0 < sigma < float("inf"):
        raise ValueError(f"{op}: sigma must be a finite number > 0, got {sigma!r}")
    # [B, H, W, K] with the classes innermost: a view of channels-last memory, a copy of any other
    classes_last, guide = prepare(probabilities.permute(0, 2, 3, 1), guide)
    # fills, not a host-to-device copy: capturable in a CUDA graph
    params = torch.cat([scalar_tensor(value, guide) for value in
                        (1.0 / sigma, 0.5 / (batch * height * (width - 1)), 0.5 / (batch * (height - 1) * width))])
    return _smoothness_map(classes_last, guide, params).sum()
