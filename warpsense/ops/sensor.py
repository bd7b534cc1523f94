"""The fused sensor op: CFA mosaic -> Poisson-Gaussian noise -> quantization in one Warp kernel (forward and
backward; the custom ops warpsense::sensor_capture and its backward), equal to the chain `cfa_mosaic` ->
`poisson_gaussian` -> `quantize_ste` (full-well mode)."""

from __future__ import annotations

import torch

from warpsense.kernels import sensor as kernels
from warpsense.ops._warp import launch, prepare, save_inputs, scalar_tensor, warp_op
from warpsense.ops.arguments import check_level, check_same_device, check_tensor
from warpsense.ops.cfa import rgb_gradient_buffer, site_reduction_buffers
from warpsense.ops.noise import noise_seeds
from warpsense.ops.quantize import check_quantize_arguments


def _sensor_backward_fake(rgb, phi, shot, read, white, seeds, image_stride, noisy, steps, grad_raw, want_rgb):
    return rgb_gradient_buffer(rgb, want_rgb), torch.empty_like(phi), torch.empty_like(shot), torch.empty_like(read)


@warp_op("sensor_capture_backward", _sensor_backward_fake)
def _sensor_capture_backward(rgb: torch.Tensor, phi: torch.Tensor, shot: torch.Tensor, read: torch.Tensor,
                             white: torch.Tensor, seeds: torch.Tensor, image_stride: int, noisy: int, steps: int,
                             grad_raw: torch.Tensor, want_rgb: bool
                             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    grad_raw = grad_raw.to(rgb.dtype).contiguous()
    tile = phi.shape[0]
    grad_rgb, partials = site_reduction_buffers(rgb, tile, want_rgb, 5)
    launch(kernels.sensor_backward, tuple(partials.shape[:2]),
           [rgb, phi, shot, read, seeds, image_stride, noisy, steps, white, grad_raw, int(want_rgb), grad_rgb,
            partials], rgb.device)
    sums = partials.sum(dim=1)
    levels = sums[:, 3:].sum(dim=0)
    return grad_rgb, sums[:, :3].reshape(tile, tile, 3).contiguous(), levels[0:1].clone(), levels[1:2].clone()


def _sensor_backward(ctx, grad_raw):
    rgb, phi, shot, read, white, seeds = ctx.saved_tensors
    want_rgb = ctx.needs_input_grad[0]
    grad_rgb, grad_phi, grad_shot, grad_read = _sensor_capture_backward(rgb, phi, shot, read, white, seeds,
                                                                        *ctx.arguments, grad_raw, want_rgb)
    return (grad_rgb if want_rgb else None), grad_phi, grad_shot, grad_read, None, None, None, None, None


@warp_op("sensor_capture", lambda rgb, *rest: rgb.new_empty(rgb.shape[0], 1, *rgb.shape[2:]), _sensor_backward,
         save_inputs)
def _sensor_capture(rgb: torch.Tensor, phi: torch.Tensor, shot: torch.Tensor, read: torch.Tensor, white: torch.Tensor,
                    seeds: torch.Tensor, image_stride: int, noisy: int, steps: int) -> torch.Tensor:
    batch, _, height, width = rgb.shape
    raw = rgb.new_empty(batch, 1, height, width)
    launch(kernels.sensor_forward, (batch, height, width),
           [rgb, phi, shot, read, seeds, image_stride, noisy, steps, white, raw], rgb.device)
    return raw


def sensor_capture(rgb: torch.Tensor, phi: torch.Tensor, shot: float | torch.Tensor | None = None,
                   read: float | torch.Tensor | None = None, seed: int | torch.Tensor = 0, bits: int | None = None,
                   white_level: float = 1.0) -> torch.Tensor:
    """Radiance to quantized RAW in one pass (eqs. 4-6 of the paper, docs/references.md; exposure is folded into
    ``phi`` by the caller).

    Args:
        rgb: [B, 3, H, W] linear irradiance.
        phi: [T, T, 3] effective spectral responses (exposure gain a(g) times the CFA responses).
        shot, read: noise levels as in `poisson_gaussian` (variance coefficient, standard deviation); None for
            both: no noise stage.
        seed: int or integer tensor [B] of per-image seeds, as in `poisson_gaussian` (the same noise draw).
        bits: ADC bit depth (1..24) with full-well level ``white_level``; None: no quantization stage.

    Returns:
        raw [B, 1, H, W], equal to quantize_ste(poisson_gaussian(cfa_mosaic(rgb, phi), shot, read, seed), bits,
        white_level) and with the same gradients (w.r.t. rgb, phi, shot and read). Once differentiable.
    """
    check_tensor("sensor_capture", "rgb", rgb, 4, "[B, 3, H, W]")
    check_tensor("sensor_capture", "phi", phi)
    check_same_device("sensor_capture", rgb=rgb, phi=phi)
    if rgb.shape[1] != 3:
        raise ValueError(f"sensor_capture: rgb must be a non-empty [B, 3, H, W] tensor, got {tuple(rgb.shape)}")
    if phi.dim() != 3 or phi.shape[0] != phi.shape[1] or phi.shape[2] != 3 or phi.shape[0] < 1:
        raise ValueError(f"sensor_capture: phi must be [T, T, 3] with T >= 1, got {tuple(phi.shape)}")
    if (shot is None) != (read is None):
        raise ValueError("sensor_capture: give both shot and read (noise) or neither")
    noisy = shot is not None
    if noisy:
        check_level("sensor_capture", "shot", shot)
        check_level("sensor_capture", "read", read)
    if bits is not None:
        check_quantize_arguments(bits, white_level, "full_well", "sensor_capture")
    if rgb.numel() >= 2**31:
        raise ValueError("sensor_capture: at most 2^31 - 1 elements per call (noise is keyed by an int32 index)")
    seeds, image_stride = noise_seeds(seed, rgb.shape[0], rgb.device, "sensor_capture")
    rgb, phi = prepare(rgb, phi)
    shot_t = scalar_tensor(shot if noisy else 0.0, rgb)
    read_t = scalar_tensor(read if noisy else 0.0, rgb)
    white = scalar_tensor(white_level, rgb)
    steps = (1 << bits) - 1 if bits is not None else 0
    return _sensor_capture(rgb, phi, shot_t, read_t, white, seeds, image_stride, int(noisy), steps)
