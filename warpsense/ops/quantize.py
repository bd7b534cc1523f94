"""ADC quantization op with a clipped straight-through gradient: Warp kernel registered into torch autograd."""

from __future__ import annotations

import torch

from warpsense.kernels import quantize as kernels
from warpsense.ops._warp import launch, prepare

QUANTIZE_MODES = ("full_well", "max")


class QuantizeSTE(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rows: torch.Tensor, white: torch.Tensor, steps: int) -> torch.Tensor:
        out = torch.empty_like(rows)
        launch(kernels.quantize_forward, tuple(rows.shape), [rows, white, steps, out], rows.device)
        ctx.save_for_backward(rows, white)
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        rows, white = ctx.saved_tensors
        grad_out = grad_out.to(rows.dtype).contiguous()
        grad_rows = torch.empty_like(rows)
        launch(kernels.quantize_backward, tuple(rows.shape), [rows, white, grad_out, grad_rows], rows.device)
        return grad_rows, None, None


def white_levels(rows: torch.Tensor, white_level: float, mode: str) -> torch.Tensor:
    """Per-image white level w [B]: ``white_level`` (full_well) or the image max (max mode; a frame whose max is
    <= 0 or not finite falls back to ``white_level``, so a black frame quantizes to 0 instead of dividing by 0)."""
    if mode == "full_well":
        return torch.full((rows.shape[0],), float(white_level), dtype=rows.dtype, device=rows.device)
    peak = rows.detach().amax(dim=1)
    return torch.where(torch.isfinite(peak) & (peak > 0), peak, torch.full_like(peak, float(white_level)))


def quantize_ste(raw: torch.Tensor, bits: int, white_level: float = 1.0, mode: str = "full_well") -> torch.Tensor:
    """Quantize to ``bits`` with 2^bits - 1 steps on [0, w], straight-through gradient (SPEC section 1).

    Q(R) = floor(clip(R, 0, w) / w * (2^b - 1) + 1/2) / (2^b - 1) * w.

    Args:
        raw: [B, ...] signal; each batch item is an image.
        bits: bit depth, 1..24.
        white_level: full-well level w (> 0) in mode "full_well"; fallback for black frames in mode "max".
        mode: "full_well" (fixed w, physical) or "max" (w = per-image max, paper eq. 6; treated as a constant
            in backward).

    Returns:
        Quantized tensor of raw's shape; gradient 1 where 0 <= R <= w, 0 outside (clipped STE).
    """
    if mode not in QUANTIZE_MODES:
        raise ValueError(f"quantize_ste: mode must be one of {QUANTIZE_MODES}, got {mode!r}")
    if not (isinstance(bits, int) and 1 <= bits <= 24):
        raise ValueError(f"quantize_ste: bits must be an int in 1..24, got {bits!r}")
    if not white_level > 0:
        raise ValueError(f"quantize_ste: white_level must be > 0, got {white_level!r}")
    if raw.dim() < 1 or raw.numel() == 0:
        raise ValueError(f"quantize_ste: raw must be a non-empty [B, ...] tensor, got {tuple(raw.shape)}")
    (raw_c,) = prepare(raw)
    rows = raw_c.reshape(raw.shape[0], -1)
    white = white_levels(rows, white_level, mode)
    return QuantizeSTE.apply(rows, white, (1 << bits) - 1).view(raw.shape)
