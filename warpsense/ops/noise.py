"""Poisson-Gaussian noise op: Warp kernel registered into torch autograd."""

from __future__ import annotations

import torch

from warpsense.kernels import noise as kernels
from warpsense.ops._warp import launch, prepare, reduction_lanes, scalar_tensor, seed_int32


class PoissonGaussian(torch.autograd.Function):
    @staticmethod
    def forward(ctx, raw: torch.Tensor, shot: torch.Tensor, read: torch.Tensor, seed: int) -> torch.Tensor:
        out = torch.empty_like(raw)
        launch(kernels.noise_forward, raw.numel(), [raw.view(-1), shot, read, seed, out.view(-1)], raw.device)
        ctx.save_for_backward(raw, shot, read)
        ctx.seed = seed
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        raw, shot, read = ctx.saved_tensors
        grad_out = grad_out.to(raw.dtype).contiguous()
        lanes = reduction_lanes(raw.numel(), raw.device)
        grad_raw = torch.empty_like(raw)
        partials = raw.new_empty(lanes, 2)
        launch(
            kernels.noise_backward,
            lanes,
            [raw.view(-1), shot, read, ctx.seed, grad_out.view(-1), grad_raw.view(-1), partials],
            raw.device,
        )
        sums = partials.sum(dim=0)
        return grad_raw, sums[0:1], sums[1:2], None


def _noise_inputs(raw, shot, read, name):
    if raw.dim() < 1 or raw.numel() == 0:
        raise ValueError(f"{name}: raw must be a non-empty tensor, got shape {tuple(raw.shape)}")
    if raw.numel() >= 2**31:
        raise ValueError(f"{name}: at most 2^31 - 1 elements per call (noise is keyed by an int32 element index)")
    return prepare(raw, scalar_tensor(shot, raw), scalar_tensor(read, raw))


def poisson_gaussian(
    raw: torch.Tensor, shot: float | torch.Tensor, read: float | torch.Tensor, seed: int
) -> torch.Tensor:
    """Add heteroscedastic Gaussian noise, the Poisson-Gaussian model of paper eq. 5.

    R' = R + sqrt(shot * max(R, 0) + read^2) * eps, eps ~ N(0, 1).

    Args:
        raw: any shape, signal R in units of the white level (typically [0, 1]).
        shot: shot-noise VARIANCE coefficient (variance = shot * R), >= 0; float or 0-d tensor (learnable).
        read: read-noise STANDARD DEVIATION, >= 0; float or 0-d tensor (learnable).
        seed: noise seed; eps[i] is a pure function of (seed, flat index i), identical on CPU and CUDA and
            regenerated in backward (nothing stored). Draw a new seed per training step.

    Returns:
        Noisy tensor of raw's shape. Gradients reach raw, shot and read; where the noise std is 0 its derivative
        is defined as 0.
    """
    out_shape = raw.shape
    raw, shot_t, read_t = _noise_inputs(raw, shot, read, "poisson_gaussian")
    return PoissonGaussian.apply(raw, shot_t, read_t, seed_int32(seed)).view(out_shape)


@torch.no_grad()
def poisson_gaussian_exact(raw: torch.Tensor, shot: float | torch.Tensor, read: float | torch.Tensor, seed: int):
    """Exact Poisson photon counts (mean R / shot, scaled back by shot) plus Gaussian read noise; not differentiable.

    Use for evaluation at low light, where the Gaussian approximation of the shot noise is poor.
    """
    out_shape = raw.shape
    raw, shot_t, read_t = _noise_inputs(raw, shot, read, "poisson_gaussian_exact")
    out = torch.empty_like(raw)
    launch(kernels.poisson_sample, raw.numel(), [raw.view(-1), shot_t, read_t, seed_int32(seed), out.view(-1)],
           raw.device)
    return out.view(out_shape)
