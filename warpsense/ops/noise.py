"""Poisson-Gaussian noise ops: Warp kernels as the custom ops warpsense::poisson_gaussian (with its backward) and
warpsense::poisson_gaussian_exact."""

from __future__ import annotations

import torch

from warpsense.kernels import noise as kernels
from warpsense.ops._warp import launch, prepare, reduction_lanes, save_inputs, scalar_tensor, seed_int32, warp_op
from warpsense.ops.arguments import check_level, check_tensor

POISSON_NORMAL_LIMIT = float(kernels.POISSON_NORMAL_LIMIT)


def noise_seeds(seed: int | torch.Tensor, batch: int, device: torch.device, op: str = "noise"
                ) -> tuple[torch.Tensor, int]:
    """(int32 seeds [batch], image_stride) for the kernels: one int seeds the whole batch, keyed by flat element
    index (image_stride 1); an integer tensor [batch] gives each image its own seed, keyed by the element's index
    within the image (image_stride 0), so an image's noise does not depend on its place in the batch."""
    if isinstance(seed, torch.Tensor):
        if seed.dtype.is_floating_point or seed.dtype == torch.bool or seed.shape != (batch,):
            raise ValueError(f"{op}: seed must be an int or an integer tensor of shape ({batch},), got {seed.dtype} "
                             f"{tuple(seed.shape)}")
        return seed.to(device=device, dtype=torch.int32), 0
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"{op}: seed must be an int or an integer tensor, got {type(seed).__name__}")
    return torch.full((batch,), seed_int32(seed), dtype=torch.int32, device=device), 1


def _sample(kernel, raw, shot, read, seeds, image_stride: int) -> torch.Tensor:
    """One thread per element of raw: a noisy sample of it (``kernel``: the Gaussian model or exact Poisson)."""
    out = torch.empty_like(raw)
    launch(kernel, raw.numel(),
           [raw.view(-1), shot, read, seeds, raw.numel() // seeds.numel(), image_stride, out.view(-1)], raw.device)
    return out


def _noise_backward_fake(raw, shot, read, seeds, image_stride, grad_out):
    return torch.empty_like(raw), torch.empty_like(shot), torch.empty_like(read)


@warp_op("poisson_gaussian_backward", _noise_backward_fake)
def _poisson_gaussian_backward(raw: torch.Tensor, shot: torch.Tensor, read: torch.Tensor, seeds: torch.Tensor,
                               image_stride: int, grad_out: torch.Tensor
                               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    grad_out = grad_out.to(raw.dtype).contiguous()
    lanes = reduction_lanes(raw.numel(), raw.device)
    grad_raw = torch.empty_like(raw)
    partials = raw.new_empty(lanes, 2)
    launch(kernels.noise_backward, lanes,
           [raw.view(-1), shot, read, seeds, raw.numel() // seeds.numel(), image_stride, grad_out.view(-1),
            grad_raw.view(-1), partials], raw.device)
    sums = partials.sum(dim=0)
    return grad_raw, sums[0:1].clone(), sums[1:2].clone()


def _noise_backward(ctx, grad_out):
    raw, shot, read, seeds = ctx.saved_tensors
    (image_stride,) = ctx.arguments
    grad_raw, grad_shot, grad_read = _poisson_gaussian_backward(raw, shot, read, seeds, image_stride, grad_out)
    return grad_raw, grad_shot, grad_read, None, None


@warp_op("poisson_gaussian", lambda raw, shot, read, seeds, image_stride: torch.empty_like(raw), _noise_backward,
         save_inputs)
def _poisson_gaussian(raw: torch.Tensor, shot: torch.Tensor, read: torch.Tensor, seeds: torch.Tensor,
                      image_stride: int) -> torch.Tensor:
    return _sample(kernels.noise_forward, raw, shot, read, seeds, image_stride)


@warp_op("poisson_gaussian_exact", lambda raw, shot, read, seeds, image_stride: torch.empty_like(raw))
def _poisson_gaussian_exact(raw: torch.Tensor, shot: torch.Tensor, read: torch.Tensor, seeds: torch.Tensor,
                            image_stride: int) -> torch.Tensor:
    return _sample(kernels.poisson_sample, raw, shot, read, seeds, image_stride)


def _noise_inputs(raw, shot, read, seed, name):
    check_tensor(name, "raw", raw)
    if raw.numel() == 0:
        raise ValueError(f"{name}: raw must be non-empty, got shape {tuple(raw.shape)}")
    if raw.numel() >= 2**31:
        raise ValueError(f"{name}: at most 2^31 - 1 elements per call (noise is keyed by an int32 element index)")
    check_level(name, "shot", shot)
    check_level(name, "read", read)
    batch = raw.shape[0] if raw.dim() > 0 else 1
    seeds, image_stride = noise_seeds(seed, batch, raw.device, name)
    raw, shot_t, read_t = prepare(raw, scalar_tensor(shot, raw), scalar_tensor(read, raw))
    return raw, shot_t, read_t, seeds, image_stride


def poisson_gaussian(
    raw: torch.Tensor, shot: float | torch.Tensor, read: float | torch.Tensor, seed: int | torch.Tensor
) -> torch.Tensor:
    """Add heteroscedastic Gaussian noise, the Poisson-Gaussian model of eq. 5 of the paper (docs/references.md).

    R' = R + sqrt(shot * max(R, 0) + read^2) * eps, eps ~ N(0, 1).

    Args:
        raw: any shape (the first dimension is the batch), signal R in units of the white level (typically [0, 1]).
        shot: shot-noise VARIANCE coefficient (variance = shot * R), >= 0; float or 0-d tensor (learnable). A
            learnable tensor that goes negative is clamped at 0 inside the square root.
        read: read-noise STANDARD DEVIATION, >= 0; float or 0-d tensor (learnable).
        seed: an int (eps[i] a pure function of (seed, flat index i)) or an integer tensor [B] of per-image seeds
            (eps a function of (seed[b], index within the image)). Identical on CPU and CUDA, regenerated in
            backward (nothing stored). Draw a new seed per training step.

    Returns:
        Noisy tensor of raw's shape. Gradients reach raw, shot and read; where the noise std is 0 its derivative
        is defined as 0. Once differentiable (double backward raises).
    """
    out_shape = raw.shape if isinstance(raw, torch.Tensor) else None
    raw, shot_t, read_t, seeds, image_stride = _noise_inputs(raw, shot, read, seed, "poisson_gaussian")
    return _poisson_gaussian(raw, shot_t, read_t, seeds, image_stride).view(out_shape)


@torch.no_grad()
def poisson_gaussian_exact(raw: torch.Tensor, shot: float | torch.Tensor, read: float | torch.Tensor,
                           seed: int | torch.Tensor):
    """Exact Poisson photon counts (mean R / shot, scaled back by shot) plus Gaussian read noise; not differentiable.

    Use for evaluation at low light, where the Gaussian approximation of the shot noise is poor. Mean counts above
    POISSON_NORMAL_LIMIT (1e4) are drawn from the normal limit (Warp's Poisson sampler is float32 with a uint32
    count); NaN and infinite inputs pass through. Seeds as in `poisson_gaussian`.
    """
    out_shape = raw.shape if isinstance(raw, torch.Tensor) else None
    raw, shot_t, read_t, seeds, image_stride = _noise_inputs(raw, shot, read, seed, "poisson_gaussian_exact")
    return _poisson_gaussian_exact(raw, shot_t, read_t, seeds, image_stride).view(out_shape)
