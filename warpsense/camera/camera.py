"""The camera: optics -> exposure -> CFA -> noise -> quantization, built from a config."""

from __future__ import annotations

import torch
from torch import nn

from warpsense.camera.cfa import CFA
from warpsense.camera.exposure import Exposure
from warpsense.camera.noise import SensorNoise
from warpsense.camera.optics import Optics
from warpsense.camera.quantizer import Quantizer
from warpsense.ops.cfa import cfa_mosaic
from warpsense.ops.sensor import sensor_capture
from warpsense.optics.lens import Lens


class Camera(nn.Module):
    """Radiance [B, 3, H, W] (linear, >= 0) -> RAW [B, 1, H, W] in units of the white level.

    Stages the config leaves out are None and cost nothing. Exposure is folded into the CFA responses, and
    exposure -> CFA -> noise -> quantization run as one fused Warp kernel (`fusable`). Without a CFA the sensor is
    monochrome (the mean of the three channels).
    """

    def __init__(self, optics: Optics | None = None, exposure: Exposure | None = None, cfa: CFA | None = None,
                 noise: SensorNoise | None = None, quantizer: Quantizer | None = None):
        super().__init__()
        self.optics = optics
        self.exposure = exposure
        self.cfa = cfa
        self.noise = noise
        self.quantizer = quantizer
        self.register_buffer("mono_phi", torch.full((1, 1, 3), 1 / 3), persistent=False)

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

    def fusable(self) -> bool:
        """Whether exposure -> CFA -> noise -> quantization run as the one fused kernel (`sensor_capture`): always,
        except for exact Poisson noise and per-image-max quantization, which take the per-stage ops."""
        noise_ok = self.noise is None or not self.noise.exact
        quantizer_ok = self.quantizer is None or self.quantizer.mode == "full_well"
        return noise_ok and quantizer_ok

    def responses(self) -> torch.Tensor:
        """[T, T, 3] effective spectral responses: exposure gain times the CFA's phi (a monochrome sensor, without a
        CFA, is the mean of the three channels: phi = 1/3)."""
        phi = self.cfa.phi() if self.cfa is not None else self.mono_phi
        return phi * self.exposure.gain() if self.exposure is not None else phi

    def forward(self, radiance: torch.Tensor, image_index: torch.Tensor | None = None) -> torch.Tensor:
        """Radiance [B, 3, H, W] -> RAW [B, 1, H, W]; ``image_index`` [B] (dataset indices) keys the eval noise."""
        image = self.optics(radiance) if self.optics is not None else radiance
        if self.fusable():
            noisy = self.noise is not None
            shot, read = self.noise.levels() if noisy else (None, None)
            seeds = self.noise.seeds(image.shape[0], image_index) if noisy else 0
            bits = self.quantizer.bits if self.quantizer is not None else None
            white = self.quantizer.white_level if self.quantizer is not None else 1.0
            return sensor_capture(image, self.responses(), shot, read, seeds, bits, white)
        raw = cfa_mosaic(image, self.responses())
        if self.noise is not None:
            raw = self.noise(raw, image_index)
        if self.quantizer is not None:
            raw = self.quantizer(raw)
        return raw
