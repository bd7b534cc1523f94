"""ADC quantization with a clipped straight-through gradient: Warp kernels as the custom ops warpsense::quantize_ste
and its backward."""

from __future__ import annotations

import torch

from warpsense.choices import QUANTIZE_MODES
from warpsense.kernels import quantize as kernels
from warpsense.ops._warp import launch, prepare, save_inputs, warp_op
from warpsense.ops.arguments import check_tensor

_FLOAT32_RANGE = (torch.finfo(torch.float32).tiny, torch.finfo(torch.float32).max)


def check_quantize_arguments(bits, white_level, mode: str, name: str) -> None:
    """Raise a one-line error for an invalid bit depth, white level or mode."""
    if mode not in QUANTIZE_MODES:
        raise ValueError(f"{name}: mode must be one of {QUANTIZE_MODES}, got {mode!r}")
    if isinstance(bits, bool) or not isinstance(bits, int):
        raise TypeError(f"{name}: bits must be an int, got {type(bits).__name__}")
    if not 1 <= bits <= 24:
        raise ValueError(f"{name}: bits must be in 1..24, got {bits!r}")
    if isinstance(white_level, bool) or not isinstance(white_level, (int, float)):
        raise TypeError(f"{name}: white_level must be a float, got {type(white_level).__name__}")
    low, high = _FLOAT32_RANGE
    if not low <= white_level <= high:
        raise ValueError(f"{name}: white_level must be finite, > 0 and representable in float32 "
                         f"({low:.3g} .. {high:.3g}), got {white_level!r}")


@warp_op("quantize_ste_backward", lambda rows, white, grad_out: torch.empty_like(rows))
def _quantize_ste_backward(rows: torch.Tensor, white: torch.Tensor, grad_out: torch.Tensor) -> torch.Tensor:
    grad_out = grad_out.to(rows.dtype).contiguous()
    grad_rows = torch.empty_like(rows)
    launch(kernels.quantize_backward, tuple(rows.shape), [rows, white, grad_out, grad_rows], rows.device)
    return grad_rows


def _quantize_backward(ctx, grad_out):
    rows, white = ctx.saved_tensors
    return _quantize_ste_backward(rows, white, grad_out), None, None


@warp_op("quantize_ste", lambda rows, white, steps: torch.empty_like(rows), _quantize_backward, save_inputs)
def _quantize_ste(rows: torch.Tensor, white: torch.Tensor, steps: int) -> torch.Tensor:
    out = torch.empty_like(rows)
    launch(kernels.quantize_forward, tuple(rows.shape), [rows, white, steps, out], rows.device)
    return out


def white_levels(rows: torch.Tensor, white_level: float, mode: str) -> torch.Tensor:
    """Per-image white level w [B]: ``white_level`` (full_well) or the image max (max mode; a frame whose max is
    <= 0 or not finite falls back to ``white_level``, so a black frame quantizes to 0 instead of dividing by 0)."""
    if mode == "full_well":
        return torch.full((rows.shape[0],), float(white_level), dtype=rows.dtype, device=rows.device)
    finite = rows.detach().nan_to_num(nan=-torch.inf, posinf=-torch.inf)
    peak = finite.amax(dim=1)  # the brightest finite pixel: one inf pixel does not clip the frame
    return torch.where(torch.isfinite(peak) & (peak > 0), peak, torch.full_like(peak, float(white_level)))


def quantize_ste(raw: torch.Tensor, bits: int, white_level: float = 1.0, mode: str = "full_well") -> torch.Tensor:
    """Quantize to ``bits`` with 2^bits - 1 steps on [0, w], straight-through gradient (docs/references.md,
    convention 1).

    Q(R) = floor(clip(R, 0, w) / w * (2^b - 1) + 1/2) / (2^b - 1) * w.

    Args:
        raw: [B, ...] signal; each batch item is an image (a 0-d tensor is one pixel).
        bits: bit depth, 1..24. Codes are computed in float64 inside the kernel for every input type, so they equal
            the exact codes of the input values (float32 arithmetic flips a code by one level
            for ~1e-3 of pixels at 16 bits, 50% at 24; docs/benchmarks.md, error against run time).
        white_level: full-well level w (> 0) in mode "full_well"; fallback for black frames in mode "max".
        mode: "full_well" (fixed w, physical) or "max" (w = per-image max, eq. 6 of the paper; treated as a constant
            in backward).

    Returns:
        Quantized tensor of raw's shape; gradient 1 where 0 <= R <= w, 0 outside (clipped STE).
    """
    check_quantize_arguments(bits, white_level, mode, "quantize_ste")
    check_tensor("quantize_ste", "raw", raw)
    if raw.numel() == 0:
        raise ValueError(f"quantize_ste: raw must be non-empty, got shape {tuple(raw.shape)}")
    (raw_c,) = prepare(raw)
    rows = raw_c.reshape(raw.shape[0] if raw.dim() else 1, -1)
    white = white_levels(rows, white_level, mode)
    return _quantize_ste(rows, white, (1 << bits) - 1).view(raw.shape)
