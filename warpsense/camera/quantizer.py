"""ADC quantization stage Q (eq. 6 of the paper as corrected in docs/references.md, convention 1)."""

from __future__ import annotations

from warpsense.camera.stage import WHAT_IF_SOURCE, SensorArguments, Stage
from warpsense.choices import QUANTIZE_MODES
from warpsense.config import QuantizeConfig, check_value
from warpsense.ops.quantize import quantize_ste


class Quantizer(Stage):
    """b-bit quantization on [0, w] with a clipped straight-through gradient; no parameters."""

    config_section = "quantize"
    what_if = {"bits": "bits"}

    @classmethod
    def check_what_if(cls, name: str, value) -> None:
        """bits: as the config checks quantize.bits (one check, the config's message)."""
        check_value(f"{cls.config_section}.{name}", value, WHAT_IF_SOURCE)

    def __init__(self, bits: int = QuantizeConfig.bits, white_level: float = QuantizeConfig.white_level,
                 mode: str = QuantizeConfig.mode):
        """Args:
            bits: ADC bit depth b (2^b - 1 steps).
            white_level: the full-well level w (units of the signal).
            mode: a `QUANTIZE_MODES` name: "full_well" (fixed w) or "max" (w = each image's maximum).
        """
        super().__init__()
        if mode not in QUANTIZE_MODES:
            raise KeyError(f"unknown quantization mode {mode!r}; valid modes: {', '.join(QUANTIZE_MODES)}")
        self.bits = bits
        self.white_level = white_level
        self.mode = mode

    def fuse(self, arguments: SensorArguments) -> bool:
        """The fused kernel quantizes on the full well; the per-image-max mode takes this stage's own op."""
        arguments.bits, arguments.white_level = self.bits, self.white_level
        return self.mode == "full_well"

    def forward(self, raw, image_index=None):
        return quantize_ste(raw, self.bits, self.white_level, self.mode)

    def extra_repr(self) -> str:
        return f"bits={self.bits}, white_level={self.white_level}, mode={self.mode}"
