"""The camera: optics -> exposure -> CFA -> noise -> quantization, built from a config."""

from __future__ import annotations

import torch
from torch import nn

from warpsense.camera.cfa import CFA
from warpsense.camera.exposure import Exposure
from warpsense.camera.noise import SensorNoise
from warpsense.camera.optics import Optics
from warpsense.camera.quantizer import Quantizer
from warpsense.optics.lens import Lens


class Camera(nn.Module):
    """Radiance [B, 3, H, W] (linear, >= 0) -> RAW [B, 1, H, W] in units of the white level.

    Stages the config leaves out are None and cost nothing. Exposure is folded into the CFA responses when both
    are present. Without a CFA the sensor is monochrome (the mean of the three channels).
    """

    def __init__(self, optics: Optics | None = None, exposure: Exposure | None = None, cfa: CFA | None = None,
                 noise: SensorNoise | None = None, quantizer: Quantizer | None = None):
        super().__init__()
        self.optics = optics
        self.exposure = exposure
        self.cfa = cfa
        self.noise = noise
        self.quantizer = quantizer

    @classmethod
    def from_config(cls, config) -> "Camera":
        """Build from a `warpsense.config.Config` (only the enabled stages are constructed)."""
        optics = exposure = cfa = noise = quantizer = None
        if config.optics.enabled:
            lens = Lens.from_json(config.optics.lens, learnable=config.optics.learnable)
            optics = Optics(lens, learnable=config.optics.learnable, normalize_mean=config.optics.normalize_mean,
                            method=config.optics.method, energy_eps=config.optics.energy_eps,
                            field_tolerance=config.optics.field_tolerance)
        if config.exposure.enabled:
            exposure = Exposure(config.exposure.gain_logit, learnable=config.exposure.learnable)
        if config.cfa.enabled:
            cfa = CFA(config.cfa.pattern, config.cfa.tile, config.cfa.mode, config.cfa.init_logit)
        if config.noise.enabled:
            noise = SensorNoise(config.noise.shot, config.noise.read, config.noise.learnable, config.noise.eval_seed)
        if config.quantize.enabled:
            quantizer = Quantizer(config.quantize.bits, config.quantize.white_level, config.quantize.mode)
        return cls(optics, exposure, cfa, noise, quantizer)

    @property
    def tile(self) -> int:
        return self.cfa.tile if self.cfa is not None else 1

    def forward(self, radiance: torch.Tensor) -> torch.Tensor:
        image = radiance
        if self.optics is not None:
            image = self.optics(image)
        gain = self.exposure.gain() if self.exposure is not None else None
        if self.cfa is not None:
            raw = self.cfa(image, gain)
        else:
            raw = image.mean(dim=1, keepdim=True)
            raw = raw * gain if gain is not None else raw
        if self.noise is not None:
            raw = self.noise(raw)
        if self.quantizer is not None:
            raw = self.quantizer(raw)
        return raw
