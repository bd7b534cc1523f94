"""Typed run configuration loaded from TOML.

`configs/default.toml` lists every key with a comment and equals the dataclass defaults below (a test checks it).
Presets in `configs/presets/` hold only overrides. Unknown sections or keys and wrongly typed values are errors that
name the offending key and what is valid.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import sys
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from warpsense.choices import (
    CFA_LAYOUTS,
    CFA_MODES,
    COMPILE_MODES,
    DATASETS,
    DEVICES,
    ON_DEVICE_MODES,
    PSF_METHODS,
    QUANTIZE_MODES,
    SELF_CAPTURING_COMPILE_MODES,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


class ConfigError(ValueError):
    """A config file or override is malformed; the message names the file and key."""


def _choices(*values: str) -> dict:
    return {"choices": values}


@dataclass
class RunConfig:
    name: str = "default"
    output_dir: str = "runs"
    seed: int = 0
    device: str = field(default="auto", metadata=_choices(*DEVICES))


@dataclass
class DataConfig:
    dataset: str = field(default="scenes", metadata=_choices(*DATASETS))
    root: str = ""
    train_split: str = "train"
    val_split: str = "val"
    crop_height: int = 96
    crop_width: int = 128
    scale_min: float = 1.0
    scale_max: float = 1.0
    hflip: bool = True
    batch_size: int = 8
    num_workers: int = 0
    holdout_prefix: str = ""
    on_device: str = field(default="auto", metadata=_choices(*ON_DEVICE_MODES))
    on_device_max_mb: int = 2048
    max_train_images: int = 0
    max_val_images: int = 0
    scenes_train: int = 256
    scenes_val: int = 32
    scene_height: int = 96
    scene_width: int = 128
    unprocess: bool = False


@dataclass
class OpticsConfig:
    enabled: bool = False
    lens: str = "phone_68deg"
    learnable: bool = False
    normalize_mean: float = 0.5
    method: str = field(default="auto", metadata=_choices(*PSF_METHODS))
    energy_eps: float = 1e-3
    field_tolerance: float = 1e-3


@dataclass
class ExposureConfig:
    enabled: bool = True
    gain_logit: float = -1.3863
    learnable: bool = True


@dataclass
class CFAConfig:
    enabled: bool = True
    pattern: str = field(default="RGGB", metadata=_choices(*CFA_LAYOUTS))
    tile: int = 2
    mode: str = field(default="softmax", metadata=_choices(*CFA_MODES))
    init_logit: float = 4.0
    temperature_start: float = 1.0
    temperature_end: float = 0.05


@dataclass
class NoiseConfig:
    enabled: bool = True
    shot: float = 0.015
    read: float = 0.002
    full_well_electrons: float = 0.0
    read_electrons: float = 0.0
    learnable: bool = False
    eval_seed: int = 1234


def noise_levels(noise: NoiseConfig) -> tuple[float, float]:
    """(shot variance coefficient, read std) in units of the white level. With ``full_well_electrons`` set the
    sensor is stated physically: a signal of s (white level = 1) holds s * FWC electrons, so its shot variance is
    s / FWC (shot = 1 / FWC) and the read noise is read_electrons / FWC; ``shot`` and ``read`` are then ignored."""
    if noise.full_well_electrons > 0:
        return 1.0 / noise.full_well_electrons, noise.read_electrons / noise.full_well_electrons
    return noise.shot, noise.read


@dataclass
class QuantizeConfig:
    enabled: bool = True
    bits: int = 10
    white_level: float = 1.0
    mode: str = field(default="full_well", metadata=_choices(*QUANTIZE_MODES))


@dataclass
class ISPConfig:
    enabled: bool = False
    gamma: float = 2.2


@dataclass
class ModelConfig:
    name: str = "dsunet"
    width: int = 16
    num_classes: int = 0
    channels_last: bool = True


@dataclass
class LossConfig:
    ohem_weight: float = 0.6
    ohem_fraction: float = 0.25
    lovasz_weight: float = 0.4
    smooth_weight: float = 0.01


@dataclass
class TrainConfig:
    epochs: int = 12
    warmup_epochs: int = 4
    lr: float = 2e-3
    weight_decay: float = 1e-4
    camera_lr_scale: float = 0.1
    camera_grad_clip: float = 0.1
    amp: bool = True
    compile: str = field(default="off", metadata=_choices(*COMPILE_MODES))
    cuda_graph: bool = False
    max_steps_per_epoch: int = 0
    time_budget_minutes: float = 0.0
    eval_every: int = 1
    plots: bool = True


@dataclass
class Config:
    run: RunConfig = field(default_factory=RunConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optics: OpticsConfig = field(default_factory=OpticsConfig)
    exposure: ExposureConfig = field(default_factory=ExposureConfig)
    cfa: CFAConfig = field(default_factory=CFAConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    quantize: QuantizeConfig = field(default_factory=QuantizeConfig)
    isp: ISPConfig = field(default_factory=ISPConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def save(self, path: str | Path) -> None:
        """Write the resolved config as JSON (atomically)."""
        from warpsense.files import write_json

        write_json(path, self.to_dict(), sort_keys=True)


CONFIG_DIR = resources.files("warpsense.configs")


def preset_names() -> list[str]:
    return sorted(p.name[:-5] for p in (CONFIG_DIR / "presets").iterdir() if p.name.endswith(".toml"))


# value ranges per key: (minimum, maximum, minimum excluded); None = unbounded. Every float must also be finite.
RANGES = {
    "run.seed": (0, None, False),
    "data.crop_height": (1, None, False), "data.crop_width": (1, None, False),
    "data.scale_min": (0, None, True), "data.scale_max": (0, None, True), "data.batch_size": (1, None, False),
    "data.num_workers": (0, 256, False), "data.on_device_max_mb": (0, None, False),
    "data.max_train_images": (0, None, False), "data.max_val_images": (0, None, False),
    "data.scenes_train": (1, None, False), "data.scenes_val": (1, None, False),
    "data.scene_height": (8, 8192, False), "data.scene_width": (8, 8192, False),
    "optics.normalize_mean": (0, None, False), "optics.energy_eps": (0, 1, False),
    "optics.field_tolerance": (0, None, False),
    "cfa.tile": (1, 8, False), "cfa.temperature_start": (0, None, True), "cfa.temperature_end": (0, None, True),
    "noise.shot": (0, None, False), "noise.read": (0, None, False),
    "noise.full_well_electrons": (0, 1e7, False), "noise.read_electrons": (0, 1e4, False),
    "quantize.bits": (1, 24, False), "quantize.white_level": (0, None, True),
    "isp.gamma": (0, None, True),
    "model.width": (1, 512, False), "model.num_classes": (0, 1024, False),
    "loss.ohem_weight": (0, None, False), "loss.ohem_fraction": (0, 1, True), "loss.lovasz_weight": (0, None, False),
    "loss.smooth_weight": (0, None, False),
    "train.epochs": (1, None, False), "train.warmup_epochs": (0, None, False), "train.lr": (0, None, True),
    "train.weight_decay": (0, None, False), "train.camera_lr_scale": (0, None, False),
    "train.camera_grad_clip": (0, None, False), "train.max_steps_per_epoch": (0, None, False),
    "train.time_budget_minutes": (0, None, False), "train.eval_every": (1, None, False),
}


def _check_range(value: Any, key: str, where: str) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"{where}: must be finite, got {value}")
    if key not in RANGES:
        return
    minimum, maximum, excluded = RANGES[key]
    if minimum is not None and (value <= minimum if excluded else value < minimum):
        raise ConfigError(f"{where}: must be {'>' if excluded else '>='} {minimum}, got {value}")
    if maximum is not None and value > maximum:
        raise ConfigError(f"{where}: must be <= {maximum}, got {value}")


def validate(config: "Config", source: str) -> "Config":
    """Checks across keys, after every file and override is applied (each error names the keys)."""
    if config.train.warmup_epochs > config.train.epochs:
        raise ConfigError(f"{source}: train.warmup_epochs ({config.train.warmup_epochs}) must be <= train.epochs "
                          f"({config.train.epochs})")
    if config.data.scale_min > config.data.scale_max:
        raise ConfigError(f"{source}: data.scale_min ({config.data.scale_min}) must be <= data.scale_max "
                          f"({config.data.scale_max})")
    if config.noise.read_electrons > 0 and config.noise.full_well_electrons == 0:
        raise ConfigError(f"{source}: noise.read_electrons needs noise.full_well_electrons (electrons at the white "
                          "level)")
    if config.train.cuda_graph and config.train.compile in SELF_CAPTURING_COMPILE_MODES:
        raise ConfigError(f"{source}: train.cuda_graph captures the whole step; train.compile = "
                          f"{config.train.compile!r} captures graphs itself (use \"off\" or \"default\" with it)")
    from warpsense.models import MODELS
    from warpsense.optics.lens import LensFileError, read_lens_spec

    if config.model.name not in MODELS:
        raise ConfigError(f"{source}: model.name: unknown model {config.model.name!r}; valid models: "
                          f"{', '.join(sorted(MODELS))}")

    try:  # a lens file is read even while optics is off: the saved config must run when it is turned on
        read_lens_spec(config.optics.lens)
    except LensFileError as error:
        raise ConfigError(f"{source}: optics.lens: {error}") from None
    name = config.run.name
    if not name or name in (".", "..") or "/" in name or "\\" in name or name != name.strip():
        raise ConfigError(f"{source}: run.name must be a plain folder name (no path separators), got {name!r}")
    return config


def _check_type(value: Any, expected: type, where: str) -> Any:
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if expected is bool:
        ok = isinstance(value, bool)
    elif expected is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, expected)
    if not ok:
        raise ConfigError(f"{where}: expected {expected.__name__}, got {type(value).__name__} {value!r}")
    return value


def _apply(config: Config, overrides: dict, source: str) -> None:
    sections = {f.name: f for f in dataclasses.fields(Config)}
    for section_name, values in overrides.items():
        if section_name not in sections:
            raise ConfigError(f"{source}: unknown section [{section_name}]; valid sections: {', '.join(sections)}")
        if not isinstance(values, dict):
            raise ConfigError(f"{source}: [{section_name}] must be a table")
        section = getattr(config, section_name)
        fields = {f.name: f for f in dataclasses.fields(section)}
        for key, value in values.items():
            where = f"{source}: {section_name}.{key}"
            if key not in fields:
                raise ConfigError(f"{where}: unknown key; valid keys of [{section_name}]: {', '.join(fields)}")
            spec = fields[key]
            expected = {"str": str, "int": int, "float": float, "bool": bool}[spec.type]
            value = _check_type(value, expected, where)
            choices = spec.metadata.get("choices")
            if choices and value not in choices:
                raise ConfigError(f"{where}: {value!r} is not one of {', '.join(choices)}")
            _check_range(value, f"{section_name}.{key}", where)
            setattr(section, key, value)


def _read_toml(path: Path, label: str) -> dict:
    try:
        return tomllib.loads(Path(path).read_text())
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{label}: invalid TOML: {error}") from None
    except OSError as error:
        raise ConfigError(f"{label}: cannot read: {error.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{label}: not UTF-8 text") from None


def parse_override(text: str) -> dict:
    """Turn ``section.key=value`` into ``{section: {key: value}}``; value is read as TOML, else as a string."""
    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise ConfigError(f"--set {text!r}: expected section.key=value")
    dotted, raw = text.split("=", 1)
    section, key = dotted.strip().split(".", 1)
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return {section: {key: value}}


def _apply_file(config: Config, name_or_path: str | Path, depth: int) -> None:
    """Apply a preset or TOML file; a top-level ``base = "preset"`` key applies that preset first."""
    path = Path(name_or_path)
    if not path.suffix and str(name_or_path) in preset_names():
        label = f"preset {name_or_path}"
        data = _read_toml(CONFIG_DIR / "presets" / f"{name_or_path}.toml", label)
    elif path.is_file():
        label = str(path)
        data = _read_toml(path, label)
    else:
        raise ConfigError(f"config {str(name_or_path)!r}: no such file or preset; presets: {', '.join(preset_names())}")
    base = data.pop("base", None)
    if base is not None:
        if not isinstance(base, str) or depth > 8:
            raise ConfigError(f"{label}: base must name a preset (and presets must not loop)")
        if base not in preset_names() and not Path(base).is_file():
            raise ConfigError(f"{label}: base {base!r}: no such preset or file; presets: {', '.join(preset_names())}")
        _apply_file(config, base, depth + 1)
    _apply(config, data, label)


def load_config(config: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Resolve a config: dataclass defaults, then a preset or TOML file, then ``--set`` overrides.

    Args:
        config: a preset name (see `preset_names()`), a path to a TOML file, or None for the defaults.
        overrides: ``section.key=value`` strings applied in order.
    """
    resolved = Config()
    if config is not None:
        _apply_file(resolved, config, depth=0)
    for text in overrides:
        _apply(resolved, parse_override(text), f"--set {text}")
    return validate(resolved, f"config {config}" if config is not None else "config")


def with_overrides(config: Config, overrides: list[str] | tuple[str, ...]) -> Config:
    """A copy of ``config`` with ``section.key=value`` overrides applied (validated like `load_config`)."""
    resolved = copy.deepcopy(config)
    for text in overrides:
        _apply(resolved, parse_override(text), f"--set {text}")
    return validate(resolved, "config")


def config_from_dict(data: dict, source: str = "config") -> Config:
    """Rebuild a Config from `Config.to_dict()` output (e.g. the JSON saved beside a checkpoint)."""
    resolved = Config()
    _apply(resolved, data, source)
    return validate(resolved, source)
