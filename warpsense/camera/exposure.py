"""Exposure stage E (eq. 3 of the paper, docs/references.md)."""

from __future__ import annotations

import math

import torch
from torch import nn

from warpsense.camera.stage import SensorArguments, Stage
from warpsense.config import ExposureConfig
from warpsense.ops.exposure import exposure, exposure_gain


class Exposure(Stage):
    """Global gain a(g) = 0.25 + 3.75 sigmoid(g) in [0.25, 4]; owns the logit g.

    a(g) reaches its bounds 0.25 and 4 at a large finite g (|g| >~ 20 in float32, where its gradient vanishes too);
    an infinite g is refused, as an infinite parameter is non-finite from the first optimizer step on.
    """

    config_section = "exposure"
    takes = gives = "rgb"

    def __init__(self, gain_logit: float = ExposureConfig.gain_logit, learnable: bool = ExposureConfig.learnable):
        """Args:
            gain_logit: the starting logit g (the default -ln 4 gives a(g) = 1).
            learnable: whether g takes gradients.
        """
        super().__init__()
        if not math.isfinite(gain_logit):
            raise ValueError(f"exposure.gain_logit must be finite, got {gain_logit}")
        self.gain_logit = nn.Parameter(torch.tensor(float(gain_logit)), requires_grad=learnable)

    def summary(self) -> dict:
        """The gain a(g) (dimensionless, in [0.25, 4])."""
        return {"exposure_gain": float(self.gain().detach())}

    def gain(self) -> torch.Tensor:
        return exposure_gain(self.gain_logit)

    def fuse(self, arguments: SensorArguments) -> bool:
        """A gain on the irradiance: folded into the responses (exact, no extra pass)."""
        arguments.multiply_gain(self.gain())
        return True

    def forward(self, image: torch.Tensor, image_index: torch.Tensor | None = None) -> torch.Tensor:
        """[B, C, H, W] -> a(g) * image."""
        return exposure(image, self.gain_logit)
