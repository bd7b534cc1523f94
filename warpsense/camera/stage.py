"""The protocol every camera stage follows. `Camera` is the only module that talks to stages: it builds them from
their config sections, composes their fused-kernel arguments, forwards the training schedule to them and applies
what-if overrides; everything else talks to the camera."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, ClassVar

import torch
from torch import nn

WHAT_IF_SOURCE = "Camera.overridden"
"""Where a refused what-if value came from, the first words of its error (`Stage.check_what_if`)."""


@dataclass
class SensorArguments:
    """The arguments of the fused sensor kernel (`warpsense.ops.sensor.sensor_capture`), filled in by the sensor
    stages in data-path order (`Stage.fuse`).

    Attributes:
        phi: [T, T, 3] spectral responses; starts as the monochrome response (1/3 per channel, T = 1).
        gain: scalar tensor multiplying the responses (exposure, any linear gain before the noise), or None.
        shot, read: noise levels (variance coefficient, standard deviation; units of the white level), or None.
        seeds: callable (batch, image_index) -> int32 [B] per-image seeds (drawn only when the capture runs).
        bits, white_level: ADC bit depth and full-well level, or bits None for no quantization.
        digital_gain: scalar tensor the camera multiplies its output by after the ADC (the network's input gain of a
            photon budget), or None.
    """

    phi: torch.Tensor
    gain: torch.Tensor | None = None
    shot: torch.Tensor | None = None
    read: torch.Tensor | None = None
    seeds: Callable[[int, torch.Tensor | None], torch.Tensor] | None = None
    bits: int | None = None
    white_level: float = 1.0
    digital_gain: torch.Tensor | None = None

    @property
    def noisy(self) -> bool:
        return self.shot is not None

    def responses(self) -> torch.Tensor:
        """[T, T, 3] effective responses: gain times phi."""
        return self.phi * self.gain if self.gain is not None else self.phi

    def multiply_gain(self, gain: torch.Tensor) -> None:
        self.gain = gain if self.gain is None else self.gain * gain


class Stage(nn.Module):
    """A camera stage: an `nn.Module` that owns its parameters, builds itself from its config section and reports
    its learned state.

    The stage's config section (a dataclass of `warpsense.config`) is its constructor's signature: the constructor
    takes the section's keys but ``enabled`` as keyword arguments, each defaulting to the section's default (e.g.
    ``temperature_end: float = CFAConfig.temperature_end``), so a stage built in Python with its defaults is the one
    the default config builds. Adding a stage: docs/guide/development.md.

    Class attributes:
        config_section: the name of the stage's ``[section]`` (its ``enabled`` key decides whether
            `Camera.from_config` builds the stage; its other keys are the constructor's arguments).
        part: "optics" for stages on the radiance image before the sensor ([B, 3, H, W] -> [B, 3, H, W]), "sensor"
            for the sensor chain that the fused kernel can run.
        takes: the signal a sensor stage's `forward` takes: "rgb" ([B, 3, H, W] irradiance) or "raw" ([B, 1, H, W]);
            the camera turns RGB into a monochrome RAW before the first "raw" stage when no stage mosaicked it.
        gives: the signal it returns ("rgb" or "raw"); a CFA takes "rgb" and gives "raw".
        what_if: override names (`Camera.overridden`) -> the attribute of this stage they set for a while.
    """

    config_section: ClassVar[str]
    part: ClassVar[str] = "sensor"
    takes: ClassVar[str] = "raw"
    gives: ClassVar[str] = "raw"
    what_if: ClassVar[dict[str, str]] = {}

    @classmethod
    def from_config(cls, section) -> "Stage":
        """Build the stage from its whole config section (a dataclass of `warpsense.config`): the constructor called
        with every key of the section but ``enabled``."""
        return cls(**{key.name: getattr(section, key.name) for key in dataclasses.fields(section)
                      if key.name != "enabled"})

    @classmethod
    def check_section(cls, section, where: str) -> None:
        """Refuse a config section this stage cannot be built from, before any work (raise ValueError naming
        ``where`` and the key). Checks of single values (types, ranges, choices) belong to the config itself."""

    @classmethod
    def check_what_if(cls, name: str, value) -> None:
        """Refuse a `what_if` value this stage cannot run with, before the camera sets it: a one-line ValueError
        "`WHAT_IF_SOURCE`: <key>: ...". An override of a config key's value is checked by the config itself
        (`warpsense.config.check_value`, e.g. quantize.bits), not again here. The default: any value."""

    @classmethod
    def check_design(cls, config, where: str) -> None:
        """Refuse a whole config in which this stage cannot work with the others (e.g. a stage that replaces
        another needs it off); ValueError naming ``where`` and the keys. The default: nothing to check."""

    def forward(self, signal: torch.Tensor, image_index: torch.Tensor | None = None) -> torch.Tensor:
        """The stage on its own (the unfused path): ``signal`` as `takes` says -> as `gives` says;
        ``image_index`` [B] keys per-image randomness in eval."""
        raise NotImplementedError(f"{type(self).__name__} does not implement forward")

    def fuse(self, arguments: SensorArguments) -> bool:
        """Add this stage's part to the fused kernel's ``arguments`` and say whether the fused kernel computes it
        exactly (a stage that returns False turns fusing off for the whole camera; it is never skipped). No side
        effects beyond ``arguments``. The default: cannot be fused."""
        return False

    def on_epoch(self, schedule, epoch: int) -> None:
        """React to the training plan at the start of ``epoch`` (0-based; ``schedule`` a
        `warpsense.train.schedule.Schedule`), e.g. anneal a temperature or drop a cache. The default: nothing."""

    def summary(self) -> dict[str, Any]:
        """The stage's learned state as JSON-ready values keyed by a name unique across stages (recorded in each
        epoch's metrics, read through `Camera.learned`); empty when it learns nothing."""
        return {}

    def draw(self, axis) -> None:
        """Draw the stage on a matplotlib ``axis`` (the run's camera.png). Stages with a picture override this;
        `Camera.pictures` counts those that do."""
