"""The camera: optics -> exposure -> CFA -> noise -> quantization, built from a config. The only module that
talks to the stages."""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from warpsense.camera.cfa import CFA
from warpsense.camera.exposure import Exposure
from warpsense.camera.noise import SensorNoise
from warpsense.camera.optics import Optics
from warpsense.camera.photons import PhotonBudget
from warpsense.camera.quantizer import Quantizer
from warpsense.camera.stage import SensorArguments, Stage
from warpsense.ops.arguments import check_indices, check_tensor
from warpsense.ops.cfa import cfa_mosaic
from warpsense.ops.sensor import sensor_capture

STAGES: dict[str, type[Stage]] = {
    "optics": Optics,
    "exposure": Exposure,
    "cfa": CFA,
    "photons": PhotonBudget,
    "noise": SensorNoise,
    "quantizer": Quantizer,
}
"""The camera's stages in data-path order: attribute name on `Camera` -> stage class (its ``config_section``
names the config section that enables and configures it)."""

SCENE_MEAN_WITHOUT_OPTICS = 0.25
"""Mean linear irradiance assumed for a capture when no optics stage normalises it (about a street frame's)."""


@dataclass(frozen=True)
class LearnedCamera:
    """What a camera has learned (or was fixed at), typed; None where the camera has no such stage.

    Attributes:
        cfa_layout: exported filter letters row by row ("RGGB", "RCCB", ...).
        cfa_responses: [T][T][3] responses in use.
        exposure_gain: the exposure gain a(g), in [0.25, 4].
        zernike_waves: a learnable lens's Zernike coefficients (waves).
        noise_shot, noise_read: noise levels (variance coefficient, standard deviation; units of the white level).
        analog_gain: a photon budget's analog gain G (dimensionless, >= 1).
        f_number, exposure_ms: the optics' f-number and exposure time (ms).
        digital_gain: a photon budget's fixed gain from ADC units to the network's input.
    """

    cfa_layout: str | None = None
    cfa_responses: list | None = None
    exposure_gain: float | None = None
    zernike_waves: list | None = None
    noise_shot: float | None = None
    noise_read: float | None = None
    analog_gain: float | None = None
    f_number: float | None = None
    exposure_ms: float | None = None
    digital_gain: float | None = None

    @classmethod
    def from_summary(cls, summary: dict) -> "LearnedCamera":
        """From `Camera.summary` (also as recorded in metrics.jsonl and checkpoints)."""
        return cls(summary.get("cfa_layout"), summary.get("cfa_phi"), summary.get("exposure_gain"),
                   summary.get("zernike_waves"), summary.get("noise_shot"), summary.get("noise_read"),
                   summary.get("analog_gain"), summary.get("f_number"), summary.get("exposure_ms"),
                   summary.get("digital_gain"))


def _tracing(x: torch.Tensor) -> bool:
    """Whether torch.compile or torch.jit.trace is tracing, x's CUDA stream is being captured or x is a meta tensor
    (shapes only): no host reads, no cached tensors."""
    return (torch.compiler.is_compiling() or torch._C._get_tracing_state() is not None or x.is_meta
            or (x.is_cuda and torch.cuda.is_current_stream_capturing()))


class Camera(nn.Module):
    """Radiance [B, 3, H, W] (linear, >= 0) -> RAW [B, 1, H, W] in units of the white level.

    Stages the config leaves out are None and cost nothing. The optics stages run first; the sensor chain runs as
    one fused Warp kernel when every sensor stage can supply its part of it (`Stage.fuse`), otherwise stage by
    stage. Without a CFA the sensor is monochrome (the mean of the three channels).

    NaN policy: radiance must be finite. A NaN or inf pixel would not stay local (the optics' mean normalisation
    spreads it over the frame and into the lens, gain and CFA gradients), so the camera rejects it with a
    ValueError. The check costs one host synchronisation per call; `check_finite = False` skips it (the training
    loop does: its radiance comes from 8-bit images, and it checks the loss and parameters each epoch instead).
    Skipped while compiling or capturing a CUDA graph, where a host read is not allowed.
    """

    check_finite: bool = True

    def __init__(self, **stages: Stage | None):
        """Args:
            **stages: stage modules by their `STAGES` names (those left out or None are absent).
        """
        super().__init__()
        unknown = set(stages) - set(STAGES)
        if unknown:
            raise TypeError(f"Camera: unknown stage(s) {', '.join(sorted(unknown))}; stages: {', '.join(STAGES)}")
        self.stage_names = tuple(STAGES)  # this camera's data path, fixed at construction
        for name in self.stage_names:
            setattr(self, name, stages.get(name))
        self.register_buffer("mono_phi", torch.full((1, 1, 3), 1 / 3), persistent=False)
        self._cache: dict | None = None  # inside `cached`: {} until the first call fills it
        # which parameters the config made learnable; training phases toggle requires_grad within this set
        self.learnable_names = frozenset(name for name, p in self.named_parameters() if p.requires_grad)

    @staticmethod
    def _resolve(config):
        from warpsense.config import Config, config_from_dict, load_config

        if isinstance(config, (str, Path)):
            return load_config(config)
        if isinstance(config, dict):
            return config_from_dict(config, "Camera.from_config")
        if not isinstance(config, Config):
            raise TypeError(f"Camera.from_config: expected a Config, preset name, TOML path or dict, got "
                            f"{type(config).__name__}")
        return config

    @classmethod
    def from_config(cls, config) -> "Camera":
        """Build from a config (only the enabled stages are constructed).

        Args:
            config: a `warpsense.config.Config` (or any object with one attribute per stage section), a preset name
                ("camvid_codesign") or TOML path (read with `load_config`), or a dict of sections (as
                `Config.to_dict()` gives; keys left out keep their defaults, unknown keys are errors).

        Raises:
            ValueError: a section the stages refuse (`check_config`), e.g. photons.enabled with noise.enabled.
        """
        config = cls._resolve(config)
        # the stages' own checks, as the system runs them: without them a photon budget would be built beside the
        # noise and exposure stages it replaces (noise drawn twice), and noise.read_electrons without a full well
        # ignored
        cls.check_config(config, "Camera.from_config")
        sections = {name: getattr(config, stage.config_section, None) for name, stage in STAGES.items()}
        return cls(**{name: stage.from_config(sections[name]) for name, stage in STAGES.items()
                      if sections[name] is not None and sections[name].enabled})

    @staticmethod
    def check_config(config, source: str = "config") -> None:
        """Every stage's checks of its section (`Stage.check_section`), enabled or not, and of how it fits the rest
        of the config (`Stage.check_design`); ValueError naming the key."""
        for stage in STAGES.values():
            section = getattr(config, stage.config_section, None)
            if section is not None:
                stage.check_section(section, source)
            stage.check_design(config, source)

    def stages(self) -> list[tuple[str, Stage]]:
        """The constructed stages in data-path order, as (attribute name, module)."""
        modules = self._modules  # (nn.Module's __getattr__ is a slow path per name; an absent stage is None or unset)
        return [(name, modules[name]) for name in self.stage_names if modules.get(name) is not None]

    def _part(self, part: str) -> list[Stage]:
        return [stage for _, stage in self.stages() if stage.part == part]

    # --- learned state -------------------------------------------------------------------------------------------

    def summary(self) -> dict:
        """The learned state of every stage (`Stage.summary`), merged: JSON-ready values."""
        return {key: value for _, stage in self.stages() for key, value in stage.summary().items()}

    def learned(self) -> LearnedCamera:
        """The learned state, typed."""
        return LearnedCamera.from_summary(self.summary())

    def layout_letters(self) -> list[list[str]] | None:
        """The exported CFA layout as T x T letters; None for a monochrome sensor."""
        return self.cfa.hard_letters() if self.cfa is not None else None

    def raw_mean(self) -> float:
        """Mean irradiance the sensor sees times the exposure gain: the optics' normalised mean (or
        `SCENE_MEAN_WITHOUT_OPTICS` where nothing normalises it) times a(g)."""
        level = self.optics.normalize_mean if self.optics is not None and self.optics.normalize_mean > 0 \
            else SCENE_MEAN_WITHOUT_OPTICS
        return level * (float(self.exposure.gain().detach()) if self.exposure is not None else 1.0)

    @property
    def tile(self) -> int:
        return self.cfa.tile if self.cfa is not None else 1

    # --- training ------------------------------------------------------------------------------------------------

    def learnable_parameters(self) -> list[nn.Parameter]:
        """The parameters the config made learnable (whether or not a training phase freezes them now)."""
        return [p for name, p in self.named_parameters() if name in self.learnable_names]

    def on_epoch(self, schedule, epoch: int) -> None:
        """Start ``epoch`` of ``schedule`` (a `warpsense.train.schedule.Schedule`): the learnable parameters train in
        its joint phase only, and every stage reacts to the plan (`Stage.on_epoch`)."""
        for parameter in self.learnable_parameters():
            parameter.requires_grad_(schedule.is_joint(epoch))
        for _, stage in self.stages():
            stage.on_epoch(schedule, epoch)

    # --- what-if evaluation --------------------------------------------------------------------------------------

    def what_if_values(self) -> dict:
        """The overrides this camera accepts (`overridden`) with their current values, e.g. {"noise_scale": 1.0,
        "bits": 10}."""
        return {name: getattr(stage, attribute) for _, stage in self.stages()
                for name, attribute in stage.what_if.items()}

    @contextlib.contextmanager
    def overridden(self, **values) -> Iterator["Camera"]:
        """Evaluate the camera at another operating point for a while, restored on exit.

        Args:
            **values: names from `what_if_values` (``noise_scale``: noise levels scaled, shot by its square;
                ``exact_noise``: true Poisson counts; ``bits``: ADC bit depth); a name no stage of this camera
                takes is a KeyError, a value its stage cannot run with a ValueError (nothing set).
        """
        owners = {name: (stage, attribute) for _, stage in self.stages() for name, attribute in stage.what_if.items()}
        unknown = set(values) - set(owners)
        if unknown:
            raise KeyError(f"Camera.overridden: {', '.join(sorted(unknown))} not accepted by this camera; accepted: "
                           f"{', '.join(owners) or 'none'}")
        for name, value in values.items():  # every value checked by its stage before any is set
            owners[name][0].check_what_if(name, value)
        saved = {name: getattr(*owners[name]) for name in values}
        try:
            for name, value in values.items():
                setattr(*owners[name], value)
            yield self
        finally:
            for name, value in saved.items():
                setattr(*owners[name], value)

    # --- inference with a fixed camera ---------------------------------------------------------------------------

    @contextlib.contextmanager
    def cached(self) -> Iterator["Camera"]:
        """Reuse what the camera derives from its parameters across calls, as `torch.nn.utils.parametrize.cached`
        does for parametrized weights: the fused sensor kernel's arguments (responses with every gain folded in,
        noise levels, the eval seeds of a batch without ``image_index``) are computed at the first call inside and
        dropped on exit. For inference with a fixed camera (a video, a latency benchmark): at batch 1 these ~30
        small kernels cost more host time than the capture itself.

        Only calls in eval mode with gradients disabled use the cache (not while compiling or capturing a CUDA
        graph); the others compute everything as usual. An in-place change of a parameter or buffer between calls
        (an optimizer step, ``load_state_dict``, ``.to``) or a what-if override (`overridden`) is noticed and
        recomputes; a change through ``.data`` or a module put in place of one of the camera's is not: keep the
        parameters and modules fixed inside. Nests; the outermost exit drops the cache.
        """
        outermost = self._cache is None
        if outermost:
            self._cache = {}
        try:
            yield self
        finally:
            if outermost:
                self._cache = None

    def _cache_key(self) -> tuple:
        # each module's own tensors read directly, the modules listed once per cache: parameters() and buffers()
        # walk the module tree through generators on every call
        modules = self._cache.get("modules")
        if modules is None:
            modules = self._cache["modules"] = list(self.modules())
        tensors = [t for module in modules for group in (module._parameters, module._buffers)
                   for t in group.values() if t is not None]
        return (tuple((t.data_ptr(), t._version) for t in tensors), tuple(self.what_if_values().items()))

    def _sensor_state(self, image: torch.Tensor, image_index: torch.Tensor | None):
        """(arguments, fusable, seeds) for this call: inside `cached`, in eval without gradients and outside
        tracing, from the cache (the responses folded in, a batch's eval seeds kept by its size); else computed."""
        seed_cache = None
        if self._cache is not None and not self.training and not torch.is_grad_enabled() and not _tracing(image):
            key = self._cache_key()
            if self._cache.get("key") != key:
                arguments, fusable = self.sensor_arguments()
                arguments = dataclasses.replace(arguments, phi=arguments.responses(), gain=None)
                self._cache.update(key=key, arguments=arguments, fusable=fusable, seeds={})
            arguments, fusable, seed_cache = self._cache["arguments"], self._cache["fusable"], self._cache["seeds"]
        else:
            arguments, fusable = self.sensor_arguments()
        if not (arguments.noisy and fusable):
            return arguments, fusable, 0
        batch = image.shape[0]
        if seed_cache is None or image_index is not None:
            return arguments, fusable, arguments.seeds(batch, image_index)
        if batch not in seed_cache:
            seed_cache[batch] = arguments.seeds(batch, None)
        return arguments, fusable, seed_cache[batch]

    # --- data path -----------------------------------------------------------------------------------------------

    def sensor_arguments(self) -> tuple[SensorArguments, bool]:
        """The fused kernel's arguments supplied by the sensor stages in order, and whether all of them can be
        fused."""
        arguments = SensorArguments(self.mono_phi)
        fusable = True
        for stage in self._part("sensor"):
            fusable = stage.fuse(arguments) and fusable
        return arguments, fusable

    def fusable(self) -> bool:
        """Whether the sensor chain runs as the one fused kernel (`sensor_capture`)."""
        return self.sensor_arguments()[1]

    def responses(self) -> torch.Tensor:
        """[T, T, 3] effective spectral responses: every gain before the noise times the CFA's phi (a monochrome
        sensor, without a CFA, is the mean of the three channels: phi = 1/3)."""
        return self.sensor_arguments()[0].responses()

    def forward(self, radiance: torch.Tensor, image_index: torch.Tensor | None = None) -> torch.Tensor:
        """Radiance [B, 3, H, W] -> RAW [B, 1, H, W]; ``image_index`` [B] (dataset indices) keys the eval noise."""
        # named here, in the camera's words: the stages' ops name their own arguments (rgb, image, seed), and a numpy
        # array or an int index would fail with an AttributeError from inside
        if isinstance(radiance, torch.Tensor) and not radiance.is_floating_point():  # most likely an sRGB frame
            raise TypeError(f"camera: radiance must be floating point (linear), got {radiance.dtype}; an sRGB frame "
                            "is decoded by warpsense.data.color.srgb_to_linear (SensingModel does it for uint8)")
        check_tensor("camera", "radiance", radiance, 4, "[B, 3, H, W] tensor")
        if radiance.shape[1] != 3:
            raise ValueError(f"camera: radiance must be [B, 3, H, W] (linear RGB), got {tuple(radiance.shape)}")
        if image_index is not None:
            check_indices("camera", "image_index", image_index, radiance.shape[0])
        if radiance.device != self.mono_phi.device:  # else the sensor op named its own arguments (rgb, phi)
            raise ValueError(f"camera: radiance is on {radiance.device}, the camera on {self.mono_phi.device}; move "
                             f"one to the other (camera.to(radiance.device))")
        # one reduction and one host read: a NaN or inf anywhere makes the sum non-finite (a sum that overflows
        # from finite values is counted exactly and passes); detached, since reading a graph-carrying tensor as a
        # number makes torch warn, and gradients with respect to the scene are a normal use
        if (self.check_finite and not _tracing(radiance)
                and not math.isfinite(float(radiance.detach().sum(dtype=torch.float64)))):
            bad = int((~torch.isfinite(radiance)).sum())
            if bad:
                raise ValueError(f"camera: radiance has {bad} non-finite values (NaN or inf) of {radiance.numel()}; "
                                 "the camera takes finite radiance only")
        image = radiance
        for stage in self._part("optics"):
            image = stage(image)
        arguments, fusable, seeds = self._sensor_state(image, image_index)
        if fusable:
            raw = sensor_capture(image, arguments.responses(), arguments.shot, arguments.read, seeds,
                                 arguments.bits, arguments.white_level)
        else:
            signal, is_rgb = image, True
            for stage in self._part("sensor"):
                if is_rgb and stage.takes == "raw":
                    signal, is_rgb = cfa_mosaic(signal, self.mono_phi), False  # a monochrome sensor
                signal = stage(signal, image_index)
                is_rgb = stage.gives == "rgb"
            raw = cfa_mosaic(signal, self.mono_phi) if is_rgb else signal
        return raw * arguments.digital_gain if arguments.digital_gain is not None else raw

    # --- pictures ------------------------------------------------------------------------------------------------

    def pictures(self) -> int:
        """How many stages have a picture (`Stage.draw`)."""
        return sum(type(stage).draw is not Stage.draw for _, stage in self.stages())

    def draw(self, axes: list) -> None:
        """Draw the stages that have a picture on ``axes`` (matplotlib axes, `pictures` of them), in data-path
        order."""
        drawable = [stage for _, stage in self.stages() if type(stage).draw is not Stage.draw]
        for axis, stage in zip(axes, drawable, strict=True):
            stage.draw(axis)


def set_finite_check(module: nn.Module, enabled: bool) -> None:
    """Turn the radiance check (`Camera.check_finite`) on or off for every camera inside ``module``."""
    for child in module.modules():
        if isinstance(child, Camera):
            child.check_finite = enabled


@contextlib.contextmanager
def cached_cameras(module: nn.Module) -> Iterator[nn.Module]:
    """`Camera.cached` for every camera inside ``module`` (a whole system) for the duration of the block."""
    with contextlib.ExitStack() as stack:
        for child in module.modules():
            if isinstance(child, Camera):
                stack.enter_context(child.cached())
        yield module
