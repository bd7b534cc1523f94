"""The camera: optics -> exposure -> CFA -> noise -> quantization, built from a config."""

from __future__ import annotations

import torch
from torch import nn

from warpsense.camera.cfa import CFA
from warpsense.camera.exposure import Exposure
from warpsense.camera.noise import SensorNoise
from warpsense.camera.optics import Optics
from warpsense.camera.quantizer import Quantizer
from warpsense.camera.stage import Stage
from warpsense.ops.cfa import cfa_mosaic
from warpsense.ops.sensor import sensor_capture

STAGES: dict[str, type[Stage]] = {
    "optics": Optics, "exposure": Exposure, "cfa": CFA, "noise": SensorNoise, "quantizer": Quantizer,
}
"""The camera's stages in data-path order: attribute name on `Camera` -> stage class (its ``config_section``
names the config section that enables and configures it)."""


class Camera(nn.Module):
    """Radiance [B, 3, H, W] (linear, >= 0) -> RAW [B, 1, H, W] in units of the white level.

    Stages the config leaves out are None and cost nothing. Exposure is folded into the CFA responses, and
    exposure -> CFA -> noise -> quantization run as one fused Warp kernel (`fusable`). Without a CFA the sensor is
    monochrome (the mean of the three channels).

    NaN policy (issue 15, D10): radiance must be finite. A NaN or inf pixel would not stay local (the optics'
    mean normalisation spreads it over the frame and into the lens, gain and CFA gradients), so the camera rejects
    it with a ValueError. The check costs one host synchronisation per call; `check_finite = False` skips it
    (the training loop does: its radiance comes from 8-bit images, and it checks the loss and parameters each
    epoch instead). Skipped while compiling or capturing a CUDA graph, where a host read is not allowed.
    """

    check_finite: bool = True

    def __init__(self, optics: Optics | None = None, exposure: Exposure | None = None, cfa: CFA | None = None,
                 noise: SensorNoise | None = None, quantizer: Quantizer | None = None):
        super().__init__()
        self.optics = optics
        self.exposure = exposure
        self.cfa = cfa
        self.noise = noise
        self.quantizer = quantizer
        self.register_buffer("mono_phi", torch.full((1, 1, 3), 1 / 3), persistent=False)
        # which parameters the config made learnable; training phases toggle requires_grad within this set
        self.learnable_names = frozenset(name for name, p in self.named_parameters() if p.requires_grad)

    @classmethod
    def from_config(cls, config) -> "Camera":
        """Build from a config (only the enabled stages are constructed).

        Args:
            config: a `warpsense.config.Config`, a preset name ("camvid_codesign") or TOML path (read with
                `load_config`, presets and ``base`` files resolved), or a dict of sections (as `Config.to_dict()`
                gives; keys left out keep their defaults, unknown keys are errors).
        """
        from pathlib import Path

        from warpsense.config import Config, config_from_dict, load_config

        if isinstance(config, (str, Path)):
            config = load_config(config)
        elif isinstance(config, dict):
            config = config_from_dict(config, "Camera.from_config")
        elif not isinstance(config, Config):
            raise TypeError(f"Camera.from_config: expected a Config, preset name, TOML path or dict, got "
                            f"{type(config).__name__}")

        sections = {name: getattr(config, stage.config_section) for name, stage in STAGES.items()}
        return cls(**{name: stage.from_config(sections[name]) for name, stage in STAGES.items()
                      if sections[name].enabled})

    def stages(self) -> list[tuple[str, Stage]]:
        """The constructed stages in data-path order, as (attribute name, module)."""
        return [(name, getattr(self, name)) for name in STAGES if getattr(self, name) is not None]

    def summary(self) -> dict:
        """The learned state of every stage (`Stage.summary`), merged: JSON-ready values."""
        return {key: value for _, stage in self.stages() for key, value in stage.summary().items()}

    def learnable_parameters(self) -> list[nn.Parameter]:
        """The parameters the config made learnable (whether or not a training phase freezes them now)."""
        return [p for name, p in self.named_parameters() if name in self.learnable_names]

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
        if self.check_finite and not torch.compiler.is_compiling() and not (
                radiance.is_cuda and torch.cuda.is_current_stream_capturing()):
            bad = int((~torch.isfinite(radiance)).sum())
            if bad:
                raise ValueError(f"camera: radiance has {bad} non-finite values (NaN or inf) of {radiance.numel()}; "
                                 "the camera takes finite radiance only")
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


def set_finite_check(module: nn.Module, enabled: bool) -> None:
    """Turn the radiance check (`Camera.check_finite`) on or off for every camera inside ``module``."""
    for child in module.modules():
        if isinstance(child, Camera):
            child.check_finite = enabled
