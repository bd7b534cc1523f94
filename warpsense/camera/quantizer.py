"""ADC quantization stage Q (paper eq. 6 as corrected in SPEC section 1)."""

from __future__ import annotations

from torch import nn

from warpsense.ops.quantize import QUANTIZE_MODES, quantize_ste


class Quantizer(nn.Module):
    """b-bit quantization on [0, w] with a clipped straight-through gradient; no parameters."""

    def __init__(self, bits: int = 10, white_level: float = 1.0, mode: str = "full_well"):
        super().__init__()
        if mode not in QUANTIZE_MODES:
            raise KeyError(f"unknown quantization mode {mode!r}; valid modes: {', '.join(QUANTIZE_MODES)}")
        self.bits = bits
        self.white_level = white_level
        self.mode = mode

    def forward(self, raw):
        return quantize_ste(raw, self.bits, self.white_level, self.mode)

    def extra_repr(self) -> str:
        return f"bits={self.bits}, white_level={self.white_level}, mode={self.mode}"
