"""Typed run configuration loaded from TOML.

`configs/default.toml` lists every key with a comment and equals the dataclass defaults below (a test checks it).
Presets in `configs/presets/` hold only overrides. Unknown sections or keys and wrongly typed values are errors that
name the offending key and what is valid.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from warpsense.choices import (
    CFA_LAYOUTS,
    CFA_MODES,
    COMPILE_MODES,
    DATASETS,
    DEVICES,
    DISTILL_MODES,
    LIGHT_LEVELS,
    MODEL_CONTEXTS,
    MODEL_INPUTS,
    MODEL_NAMES,
    ON_DEVICE_MODES,
    PSF_METHODS,
    QUANTIZE_MODES,
    RENDER_PRECISIONS,
    SCALE_FILLS,
    SCENE_SPLITS,
    SELF_CAPTURING_COMPILE_MODES,
)
from warpsense.resources import CONFIG_DIR

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


class ConfigError(ValueError):
    """A config file or override is malformed; the message names the file and key."""


def _field(default, *, choices: tuple | None = None, minimum: float | None = None, maximum: float | None = None,
           exclusive: bool = False):
    """A config key with its valid values: one of ``choices``, or within [``minimum``, ``maximum``] (``exclusive``:
    the minimum itself excluded); every float must also be finite."""
    metadata = {}
    if choices is not None:
        metadata["choices"] = tuple(choices)
    if minimum is not None or maximum is not None:
        metadata["range"] = (minimum, maximum, exclusive)
    return field(default=default, metadata=metadata)


@dataclass
class RunConfig:
    name: str = "default"
    output_dir: str = "runs"
    seed: int = _field(0, minimum=0)
    device: str = _field("auto", choices=DEVICES)
    deterministic: bool = False


@dataclass
class DataConfig:
    dataset: str = _field("scenes", choices=DATASETS)
    root: str = ""
    classes_file: str = ""
    train_split: str = "train"
    val_split: str = "val"
    crop_height: int = _field(96, minimum=2)  # 2: the smoothness loss compares neighbouring pixels
    crop_width: int = _field(128, minimum=2)
    scale_min: float = _field(1.0, minimum=0, exclusive=True)
    scale_max: float = _field(1.0, minimum=0, exclusive=True)
    scale_fill: str = _field("cover", choices=SCALE_FILLS)
    paste_classes: str = ""
    paste_probability: float = _field(0.5, minimum=0, maximum=1)
    hflip: bool = True
    batch_size: int = _field(8, minimum=1)
    num_workers: int = _field(0, minimum=0, maximum=256)
    holdout_prefix: str = ""
    holdout_sequence: str = ""
    holdout_block: int = _field(0, minimum=0)
    holdout_blocks: int = _field(5, minimum=2, maximum=1000)
    block_buffer: int = _field(30, minimum=0)
    on_device: str = _field("auto", choices=ON_DEVICE_MODES)
    on_device_max_mb: int = _field(2048, minimum=0)
    max_train_images: int = _field(0, minimum=0)
    max_val_images: int = _field(0, minimum=0)
    scenes_train: int = _field(256, minimum=1)
    scenes_val: int = _field(32, minimum=1)
    scene_height: int = _field(96, minimum=8, maximum=8192)
    scene_width: int = _field(128, minimum=8, maximum=8192)
    scene_sequences: int = _field(1, minimum=1, maximum=1024)
    jitter_stops: float = _field(0.0, minimum=0, maximum=16)
    jitter_gamma: float = _field(0.0, minimum=0, maximum=10)
    jitter_white_balance: float = _field(0.0, minimum=0, maximum=2)
    jitter_vignetting: float = _field(0.0, minimum=0, maximum=1)


# The camera's stage sections (`warpsense.camera.camera.STAGES`): each is its stage's constructor's keyword arguments,
# every key but `enabled`, with the constructor's defaults (`Stage.from_config`), so that a stage built in Python is
# the one the default config builds. They live here, not beside their stages, so that reading a config (the CLI's
# parser, a study plan) loads no torch.


@dataclass
class OpticsConfig:
    enabled: bool = False
    lens: str = "phone_68deg"
    learnable: bool = False
    normalize_mean: float = _field(0.5, minimum=0)
    method: str = _field("auto", choices=PSF_METHODS)
    render_precision: str = _field("float32", choices=RENDER_PRECISIONS)
    energy_eps: float = _field(0.001, minimum=0, maximum=1)
    field_tolerance: float = _field(0.001, minimum=0)
    f_number: float = _field(0.0, minimum=0, maximum=64)
    f_number_learnable: bool = False
    f_number_min: float = _field(1.4, minimum=0.5, maximum=64)
    f_number_max: float = _field(8.0, minimum=0.5, maximum=64)
    exposure_ms: float = _field(10.0, minimum=0, maximum=1000, exclusive=True)
    exposure_learnable: bool = False
    exposure_ms_min: float = _field(1.0, minimum=0, maximum=1000, exclusive=True)
    exposure_ms_max: float = _field(30.0, minimum=0, maximum=1000, exclusive=True)
    corner_speed_px_per_ms: float = _field(0.0, minimum=0, maximum=100)


@dataclass
class ExposureConfig:
    enabled: bool = True
    gain_logit: float = -1.3863
    learnable: bool = True


@dataclass
class CFAConfig:
    enabled: bool = True
    pattern: str = _field("RGGB", choices=tuple(CFA_LAYOUTS))
    tile: int = _field(2, minimum=1, maximum=8)
    mode: str = _field("softmax", choices=CFA_MODES)
    init_logit: float = 4.0
    temperature_start: float = _field(1.0, minimum=0, exclusive=True)
    temperature_end: float = _field(0.05, minimum=0, exclusive=True)
    candidates: str = "RGBC"


@dataclass
class PhotonsConfig:
    enabled: bool = False
    light: str = _field("night", choices=tuple(LIGHT_LEVELS))
    mid_grey_electrons: float = _field(0.0, minimum=0, maximum=1e7)
    pixel_pitch_um: float = _field(3.0, minimum=0, maximum=100, exclusive=True)
    quantum_efficiency: float = _field(0.6, minimum=0, maximum=1, exclusive=True)
    full_well_electrons: float = _field(6000.0, minimum=0, maximum=1e7, exclusive=True)
    read_electrons: float = _field(2.0, minimum=0, maximum=1e4)
    analog_gain: float = _field(1.0, minimum=1, maximum=1e4)
    gain_learnable: bool = False
    gain_max: float = _field(64.0, minimum=1, maximum=1e4, exclusive=True)
    digital_gain: float = _field(0.0, minimum=0)
    eval_seed: int = 1234


@dataclass
class NoiseConfig:
    enabled: bool = True
    shot: float = _field(0.015, minimum=0)
    read: float = _field(0.002, minimum=0)
    full_well_electrons: float = _field(0.0, minimum=0, maximum=10000000.0)
    read_electrons: float = _field(0.0, minimum=0, maximum=10000.0)
    learnable: bool = False
    eval_seed: int = 1234


@dataclass
class QuantizeConfig:
    enabled: bool = True
    bits: int = _field(10, minimum=1, maximum=24)
    white_level: float = _field(1.0, minimum=0, exclusive=True)
    mode: str = _field("full_well", choices=QUANTIZE_MODES)


@dataclass
class ISPConfig:
    enabled: bool = False
    gamma: float = _field(2.2, minimum=0, exclusive=True)


@dataclass
class ModelConfig:
    name: str = _field("dsunet", choices=MODEL_NAMES)
    width: int = _field(16, minimum=1, maximum=512)
    context: str = _field("none", choices=MODEL_CONTEXTS)
    squeeze: bool = True
    full_width: int = _field(0, minimum=0, maximum=512)
    full_depth: int = _field(1, minimum=1, maximum=8)
    num_classes: int = _field(0, minimum=0, maximum=1024)
    channels_last: bool = True
    input: str = _field("sensor", choices=MODEL_INPUTS)


@dataclass
class LossConfig:
    ohem_weight: float = _field(0.6, minimum=0)
    ohem_fraction: float = _field(0.25, minimum=0, maximum=1, exclusive=True)
    lovasz_weight: float = _field(0.4, minimum=0)
    smooth_weight: float = _field(0.01, minimum=0)
    teacher: str = ""
    distill_weight: float = _field(0.0, minimum=0)
    distill_temperature: float = _field(1.0, minimum=0, exclusive=True)
    distill_mode: str = _field("pixel", choices=DISTILL_MODES)


@dataclass
class TrainConfig:
    epochs: int = _field(12, minimum=1)
    warmup_epochs: int = _field(4, minimum=0)
    lr: float = _field(0.002, minimum=0, exclusive=True)
    weight_decay: float = _field(0.0001, minimum=0)
    camera_lr_scale: float = _field(0.1, minimum=0)
    camera_grad_clip: float = _field(0.1, minimum=0)
    amp: bool = True
    compile: str = _field("off", choices=COMPILE_MODES)
    cuda_graph: bool = False
    micro_batch: int = _field(0, minimum=0)
    sync_batchnorm: bool = True
    max_steps_per_epoch: int = _field(0, minimum=0)
    time_budget_minutes: float = _field(0.0, minimum=0)
    eval_every: int = _field(1, minimum=1)
    eval_batch_size: int = _field(0, minimum=0)
    checkpoint_every: int = _field(1, minimum=1)
    plots: bool = True


@dataclass
class Config:
    run: RunConfig = field(default_factory=RunConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optics: OpticsConfig = field(default_factory=OpticsConfig)
    exposure: ExposureConfig = field(default_factory=ExposureConfig)
    cfa: CFAConfig = field(default_factory=CFAConfig)
    photons: PhotonsConfig = field(default_factory=PhotonsConfig)
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


def preset_names() -> list[str]:
    return sorted(p.name[:-5] for p in (CONFIG_DIR / "presets").iterdir() if p.name.endswith(".toml"))


def _check_range(value: Any, spec: dataclasses.Field, where: str) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"{where}: must be finite, got {value}")
    if "range" not in spec.metadata:
        return
    minimum, maximum, excluded = spec.metadata["range"]
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
    if config.train.cuda_graph and config.train.compile in SELF_CAPTURING_COMPILE_MODES:
        raise ConfigError(f"{source}: train.cuda_graph captures the whole step; train.compile = "
                          f"{config.train.compile!r} captures graphs itself (use \"off\" or \"default\" with it)")
    if config.train.micro_batch and config.train.cuda_graph:
        raise ConfigError(f"{source}: train.micro_batch splits the step for a memory-bound (CPU) run; with "
                          "train.cuda_graph use the whole batch (train.micro_batch = 0)")
    for low, high in (("f_number_min", "f_number_max"), ("exposure_ms_min", "exposure_ms_max")):
        if getattr(config.optics, low) > getattr(config.optics, high):
            raise ConfigError(f"{source}: optics.{low} ({getattr(config.optics, low)}) must be <= optics.{high} "
                              f"({getattr(config.optics, high)})")
    for key in ("train_split", "val_split"):
        if config.data.dataset == "scenes" and getattr(config.data, key) not in SCENE_SPLITS:
            raise ConfigError(f"{source}: data.{key} = {getattr(config.data, key)!r}: the generated scenes have the "
                              f"splits {', '.join(SCENE_SPLITS)}")
    if config.data.classes_file and config.data.dataset != "folder":
        raise ConfigError(f"{source}: data.classes_file = {config.data.classes_file!r} is read by data.dataset = "
                          f"\"folder\" only (the dataset is {config.data.dataset!r}, with its own classes)")
    held_out = [f"data.{key}" for key in ("holdout_sequence", "holdout_block", "holdout_prefix")
                if getattr(config.data, key)]
    if len(held_out) > 1:
        raise ConfigError(f"{source}: {' and '.join(held_out)} {'both' if len(held_out) == 2 else 'all'} hold frames "
                          "out; set one")
    if config.data.holdout_block > config.data.holdout_blocks:
        raise ConfigError(f"{source}: data.holdout_block = {config.data.holdout_block}: the folds are 1.."
                          f"{config.data.holdout_blocks} (data.holdout_blocks)")
    sequence = config.data.holdout_sequence
    if sequence != sequence.strip() or "/" in sequence or "\\" in sequence:
        raise ConfigError(f"{source}: data.holdout_sequence must be a sequence name, got {sequence!r}")
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


EVERY_VALUE = object()
"""`Retired.remaining` of a key that did nothing without another retired key: any value of it is harmless."""


@dataclass(frozen=True)
class Retired:
    """A config key (or one value of a key) removed because it was not adopted; docs/records/history.md says why (the
    measurements).

    Attributes:
        what: what it did, for the error message.
        remaining: the value that asks for the behaviour that stayed (`EVERY_VALUE`: any): a saved run's or
            checkpoint's config holding it is read as if the key were absent, since it trained as today's code does.
        verdict: why it went, in a few words.
    """

    what: str
    remaining: Any = None
    verdict: str = "measured, not adopted"


RETIRED = {
    "data.unprocess": Retired("Brooks et al. unprocessing of the sRGB radiance", False,
                              "never enabled by a preset or study, never measured"),
    "model.decoder_join": Retired("decoder joins projected by a 1x1 convolution", "concat"),
    "model.input_transform": Retired("the generalised Anscombe transform of the network's input", "linear"),
    "model.anscombe_offset": Retired("the offset of the Anscombe input transform", EVERY_VALUE),
    "loss.lovasz_stride": Retired("the Lovasz term on every Nth pixel", 1),
    "loss.class_balance": Retired("class-frequency weights on the OHEM pixels", 0.0),
    "noise.train_scale_min": Retired("noise levels drawn per training step (lower end)", 1.0),
    "noise.train_scale_max": Retired("noise levels drawn per training step (upper end)", 1.0),
    "train.ema_decay": Retired("weight EMA: an exponential moving average of the weights, evaluated and saved", 0.0,
                               "0.999 not distinguishable from none on val and on held-out drives"),
}
"""Retired keys ("section.key"): any config naming one is refused with a one-line error saying so, except a saved
run's config holding its `Retired.remaining` value (dropped)."""

RETIRED_VALUES = {
    ("model.name", "packunet"): Retired("PackUNet, the network with the 2 x 2 CFA tile packed into channels"),
    ("loss.distill_mode", "channel"): Retired("channel-wise distillation: each class's logit map matched over the "
                                              "image's pixels", verdict="lower than none on every seed on val"),
}
"""Retired values of keys that stay ("section.key", value): refused wherever they appear."""


def _retired_error(name: str, retired: Retired, source: str, saved: bool) -> ConfigError:
    """The one-line error for the retired key or value ``name`` met in ``source``."""
    if saved:
        remedy = f"{source} asks for it: read that run with the warpsense version that made it"
    elif source.startswith("--set "):
        remedy = f"drop {source}"
    else:
        remedy = f"remove it from {source}"
    return ConfigError(f"{name} was retired ({retired.what}; {retired.verdict}: docs/records/history.md); {remedy}")


def _apply(config: Config, overrides: dict, source: str, saved: bool = False) -> None:
    """Set each ``{section: {key: value}}`` of ``overrides`` on ``config``, checked; ``saved``: the overrides are a
    saved run's config (`config_from_dict`), whose `RETIRED` keys at their remaining value are dropped."""
    sections = {f.name: f for f in dataclasses.fields(Config)}
    for section_name, values in overrides.items():
        if section_name not in sections and not isinstance(values, dict):
            owners = [name for name, f in sections.items()
                      if section_name in {key.name for key in dataclasses.fields(f.default_factory)}]
            hint = f"; it is a key of [{'], ['.join(owners)}]" if owners else ""
            raise ConfigError(f"{source}: {section_name} = {values!r} is outside any section (keys go under their "
                              f"[section]){hint}")
        if section_name not in sections:
            raise ConfigError(f"{source}: unknown section [{section_name}]; valid sections: {', '.join(sections)}")
        if not isinstance(values, dict):
            raise ConfigError(f"{source}: [{section_name}] must be a table")
        section = getattr(config, section_name)
        for key, value in values.items():
            dotted = f"{section_name}.{key}"
            retired = RETIRED.get(dotted)
            if retired is not None:
                if saved and retired.remaining in (EVERY_VALUE, value):
                    continue
                raise _retired_error(f"{dotted} = {value!r}" if saved else dotted, retired, source, saved)
            if isinstance(value, str) and (dotted, value) in RETIRED_VALUES:
                raise _retired_error(f"{dotted} = {value!r}", RETIRED_VALUES[dotted, value], source, saved)
            setattr(section, key, check_value(dotted, value, source))


def check_value(key: str, value: Any, source: str = "config") -> Any:
    """One value of the config key ``key`` ("section.key") checked as a config file or --set line giving it is: the
    key known, the value's type, choices and range; returns it as the config holds it (an int given for a float key
    as a float), else raises the loader's one-line ConfigError, "<source>: <key>: ...". The one check of single
    values: the loader and the camera's what-if overrides (`warpsense.camera.stage.Stage.check_what_if`) call it."""
    section_name, _, name = key.partition(".")
    sections = {f.name: f.default_factory for f in dataclasses.fields(Config)}
    if section_name not in sections:
        raise ConfigError(f"{source}: unknown section [{section_name}]; valid sections: {', '.join(sections)}")
    fields = {f.name: f for f in dataclasses.fields(sections[section_name])}
    where = f"{source}: {key}"
    if name not in fields:
        raise ConfigError(f"{where}: unknown key; valid keys of [{section_name}]: {', '.join(fields)}")
    spec = fields[name]
    expected = {"str": str, "int": int, "float": float, "bool": bool}[spec.type]
    value = _check_type(value, expected, where)
    choices = spec.metadata.get("choices")
    if choices and value not in choices:
        raise ConfigError(f"{where}: {value!r} is not one of {', '.join(choices)}")
    _check_range(value, spec, where)
    return value


def read_toml(path: Path, label: str) -> dict:
    try:
        return tomllib.loads(Path(path).read_text())
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{label}: invalid TOML: {error}") from None
    except OSError as error:
        raise ConfigError(f"{label}: cannot read: {error.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{label}: not UTF-8 text") from None


def flatten_keys(data: dict, prefix: str = "") -> dict:
    """Nested tables as dotted keys: ``{"optics": {"f_number": 2}}`` -> ``{"optics.f_number": 2}``."""
    flat = {}
    for key, value in data.items():
        if isinstance(value, dict):
            flat.update(flatten_keys(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


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
        data = read_toml(CONFIG_DIR / "presets" / f"{name_or_path}.toml", label)
    elif path.is_file():
        label = str(path)
        data = read_toml(path, label)
    else:
        raise ConfigError(f"config {str(name_or_path)!r}: no such file or preset; presets: {', '.join(preset_names())}")
    if all(isinstance(value, dict) and not value for value in data.values()):
        # an empty file (or one of comments and empty sections) is more likely a mistake, the wrong file or one not
        # yet saved, than a request for the defaults, which leaving out --config gives
        raise ConfigError(f"{label}: the config file sets no key (empty); give it keys or a base preset, or leave "
                          f"--config out for the defaults")
    base = data.pop("base", None)
    if base is not None:
        if not isinstance(base, str) or depth > 8:
            raise ConfigError(f"{label}: base must name a preset (and presets must not loop)")
        if base not in preset_names() and not Path(base).is_file():
            raise ConfigError(f"{label}: base {base!r}: no such preset or file; presets: {', '.join(preset_names())}")
        _apply_file(config, base, depth + 1)
    _apply(config, data, label)


def _check_overrides(overrides, function: str) -> None:
    """``overrides`` must be a sequence of strings: a single string would be read one character at a time (its
    first letter refused as "--set 'n': expected section.key=value")."""
    if not isinstance(overrides, (list, tuple)) or not all(isinstance(text, str) for text in overrides):
        raise TypeError(f"{function}: overrides must be a list of 'section.key=value' strings, got "
                        f"{overrides!r}" + (f" (write [{overrides!r}])" if isinstance(overrides, str) else ""))


def load_config(config: str | Path | list | tuple | None = None,
                overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Resolve a config: dataclass defaults, then a preset or TOML file, then ``--set`` overrides.

    Args:
        config: a preset name (see `preset_names()`), a path to a TOML file, a list of them (applied in order, each
            over the last), or None for the defaults.
        overrides: ``section.key=value`` strings applied in order (a list or tuple of them).
    """
    _check_overrides(overrides, "load_config")
    resolved = Config()
    files = [] if config is None else list(config) if isinstance(config, (list, tuple)) else [config]
    for name_or_path in files:  # else Path() fails: "expected str, bytes or os.PathLike object, not dict"
        if not isinstance(name_or_path, (str, os.PathLike)):
            hint = " (a dict of sections: config_from_dict)" if isinstance(name_or_path, dict) else ""
            raise TypeError(f"load_config: config must be a preset name, a TOML path or a list of them, got "
                            f"{type(name_or_path).__name__}{hint}")
    for name_or_path in files:
        _apply_file(resolved, name_or_path, depth=0)
    for text in overrides:
        _apply(resolved, parse_override(text), f"--set {text}")
    return validate(resolved, f"config {' + '.join(map(str, files))}" if files else "config")


def with_overrides(config: Config, overrides: list[str] | tuple[str, ...]) -> Config:
    """A copy of ``config`` with ``section.key=value`` overrides applied (validated like `load_config`)."""
    _check_overrides(overrides, "with_overrides")
    resolved = copy.deepcopy(config)
    for text in overrides:
        _apply(resolved, parse_override(text), f"--set {text}")
    return validate(resolved, "config")


def config_from_dict(data: dict, source: str = "config") -> Config:
    """Rebuild a Config from `Config.to_dict()` output (e.g. the JSON saved beside a checkpoint). A key added since
    takes its default; a `RETIRED` key at the value of the behaviour that stayed is dropped (the run trained as
    today's code does), at any other value it is a `ConfigError`."""
    resolved = Config()
    _apply(resolved, data, source, saved=True)
    return validate(resolved, source)
