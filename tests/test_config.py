import copy
import dataclasses
import json
import sys

import pytest

from warpsense.config import (
    CONFIG_DIR,
    EVERY_VALUE,
    RETIRED,
    RETIRED_VALUES,
    Config,
    ConfigError,
    check_value,
    config_from_dict,
    load_config,
    parse_override,
    preset_names,
    with_overrides,
)

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib


def test_default_toml_lists_every_key_with_defaults_and_comments():
    text = (CONFIG_DIR / "default.toml").read_text()
    data = tomllib.loads(text)
    assert data == Config().to_dict()
    for line in text.splitlines():
        if "=" in line and not line.lstrip().startswith("#"):
            assert "#" in line, f"key without a comment: {line}"


@pytest.mark.parametrize("name", preset_names())
def test_presets_load_and_hold_only_overrides(name):
    config = load_config(name)
    data = tomllib.loads((CONFIG_DIR / "presets" / f"{name}.toml").read_text())
    defaults = Config().to_dict()
    for section, values in data.items():
        if section == "base":
            continue
        for key in values:
            assert key in defaults[section]
    assert config.run.name == data["run"]["name"]


def test_preset_base_chain_and_overrides():
    config = load_config("camvid_ablation_no_optics", ["train.epochs=3", "train.warmup_epochs=1", "data.hflip=false",
                                                       "optics.lens=phone_80deg"])
    assert config.data.dataset == "camvid"  # from the base preset
    assert config.optics.enabled is False  # the ablation's own change
    assert config.train.epochs == 3 and config.data.hflip is False and config.optics.lens == "phone_80deg"



@pytest.mark.parametrize("key, value", [("quantize.bits", 0), ("quantize.bits", 25), ("quantize.bits", 8.0),
                                        ("quantize.bits", True), ("quantize.mode", "peak"), ("noise.shot", -1.0),
                                        ("noise.shot", "high"), ("quantize.bitz", 8), ("quantiz.bits", 8)])
def test_check_value_is_the_loaders_check_of_one_key(key, value):
    """`check_value`, the one check of a single value (the camera's what-if overrides call it), raises exactly the
    loader's one-line error for the same value, and returns a good value as the config holds it."""
    text = f"{key}={json.dumps(value)}"
    with pytest.raises(ConfigError) as loaded:
        load_config(None, [text])
    with pytest.raises(ConfigError) as checked:
        check_value(key, value, f"--set {text}")
    assert str(checked.value) == str(loaded.value) and "\n" not in str(checked.value)
    assert check_value("quantize.bits", 12) == 12 and check_value("noise.shot", 1) == 1.0
    assert isinstance(check_value("noise.shot", 1), float)


def test_unknown_keys_and_types_are_errors(tmp_path):
    with pytest.raises(ConfigError, match="train.epoch: unknown key; valid keys of \\[train\\]: epochs"):
        load_config(None, ["train.epoch=3"])
    with pytest.raises(ConfigError, match="unknown section \\[trian\\]"):
        load_config(None, ["trian.epochs=3"])
    with pytest.raises(ConfigError, match="train.epochs: expected int, got str"):
        load_config(None, ["train.epochs=many"])
    with pytest.raises(ConfigError, match="quantize.mode: 'peak' is not one of full_well, max"):
        load_config(None, ["quantize.mode=peak"])
    with pytest.raises(ConfigError, match="expected section.key=value"):
        parse_override("epochs=3")
    bad = tmp_path / "bad.toml"
    bad.write_text("[noise]\nshot = 'high'\n")
    with pytest.raises(ConfigError, match=f"{bad}: noise.shot: expected float"):
        load_config(bad)
    bad.write_text("epochs = 3\n[noise]\nshot = 0.1\n")
    with pytest.raises(ConfigError, match=f"^{bad}: epochs = 3 is outside any section .*a key of \\[train\\]$"):
        load_config(bad)
    bad.write_text("[noise\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="no such file or preset"):
        load_config("nope")


def test_overrides_given_as_one_string_are_a_type_error_showing_the_list():
    """A string is a sequence too: read one character at a time, its first letter was refused as "--set 'n':
    expected section.key=value"."""
    with pytest.raises(TypeError, match=r"^load_config: overrides must be a list of 'section.key=value' strings, "
                                        r"got 'noise.shot=0.1' \(write \['noise.shot=0.1'\]\)$"):
        load_config(None, "noise.shot=0.1")
    with pytest.raises(TypeError, match="^with_overrides: overrides must be a list"):
        with_overrides(Config(), "noise.shot=0.1")
    assert load_config(None, ("noise.shot=0.1",)).noise.shot == 0.1  # a tuple, as the annotation says


@pytest.mark.parametrize("config, shown", [({"noise": {"shot": 0.1}}, r"dict \(a dict of sections: config_from_dict\)"),
                                           (3, "int"), (["camvid", 3.0], "float")])
def test_a_config_that_is_no_name_or_path_is_a_type_error_naming_it(config, shown):
    """Path() refused it from inside: "expected str, bytes or os.PathLike object, not dict"."""
    with pytest.raises(TypeError, match=f"^load_config: config must be a preset name, a TOML path or a list of "
                                        f"them, got {shown}$"):
        load_config(config)


def test_int_accepted_for_float_and_save_round_trip(tmp_path):
    config = load_config(None, ["noise.shot=1", "run.name=\"x y\""])
    assert config.noise.shot == 1.0 and isinstance(config.noise.shot, float)
    config.save(tmp_path / "config.json")
    saved = json.loads((tmp_path / "config.json").read_text())
    assert saved["run"]["name"] == "x y"
    assert dataclasses.asdict(config_from_dict(saved)) == dataclasses.asdict(config)


@pytest.mark.parametrize("override,message", [
    ("train.epochs=0", "train.epochs: must be >= 1, got 0"),
    ("train.lr=-0.1", "train.lr: must be > 0"),
    ("train.lr=inf", "train.lr: must be finite"),
    ("train.lr=nan", "train.lr: must be finite"),
    ("loss.ohem_fraction=0", "loss.ohem_fraction: must be > 0"),
    ("cfa.temperature_end=0", "cfa.temperature_end: must be > 0"),
    ("quantize.bits=0", "quantize.bits: must be >= 1"),
    ("quantize.bits=64", "quantize.bits: must be <= 24"),
    ("data.crop_height=1", "data.crop_height: must be >= 2"),
    ("train.eval_every=0", "train.eval_every: must be >= 1"),
    ("train.checkpoint_every=0", "train.checkpoint_every: must be >= 1"),
    ("noise.shot=-1", "noise.shot: must be >= 0"),
    ("run.name=../../etc", "run.name must be a plain folder name"),
    ("train.warmup_epochs=20", "train.warmup_epochs \\(20\\) must be <= train.epochs"),
    ("data.scale_min=2.0", "data.scale_min \\(2.0\\) must be <= data.scale_max"),
])
def test_values_out_of_range_are_refused_naming_the_key(override, message, tmp_path):
    """Issue 14 item 7: rejected at load, before any directory exists."""
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override, f"run.output_dir={tmp_path / 'out'}"])
    assert not (tmp_path / "out").exists()


def test_cuda_graph_refuses_self_capturing_compile_modes():
    with pytest.raises(ConfigError, match="train.cuda_graph.*reduce-overhead"):
        load_config(None, ["train.cuda_graph=true", "train.compile=reduce-overhead"])
    assert load_config(None, ["train.cuda_graph=true", "train.compile=default"]).train.cuda_graph


RETIRED_VALUE = ("model.name", "packunet")


@pytest.mark.parametrize("key", [*RETIRED, *("=".join(key) for key in RETIRED_VALUES)])
def test_a_retired_key_or_value_is_refused_in_one_line_naming_it_and_where_to_read_why(key, tmp_path):
    """Every retired key (any value, even that of the behaviour that stayed: a config asking for it is out of date)
    and retired value is refused from --set and from a TOML file, by a one-line error naming it, saying it was
    retired and pointing at docs/records/history.md."""
    key, _, value = key.partition("=")
    retired = RETIRED.get(key) or RETIRED_VALUES[key, value]
    named = f"{key} = {value!r}" if value else key
    text = f'{key}="{value}"' if value else f"{key}=1"
    why = f"{named} was retired ({retired.what}; {retired.verdict}: docs/records/history.md)"
    with pytest.raises(ConfigError) as refused:
        load_config(None, [text])
    assert str(refused.value) == f"{why}; drop --set {text}"
    section, name = key.split(".")
    path = tmp_path / "old.toml"
    path.write_text(f"[{section}]\n{name} = {text.split('=', 1)[1]}\n")
    with pytest.raises(ConfigError) as refused:
        load_config(path)
    assert str(refused.value) == f"{why}; remove it from {path}"


def test_a_saved_config_drops_retired_keys_that_ask_for_the_behaviour_that_stayed():
    """A run or checkpoint saved before a key was retired holds it: at the value of the behaviour that stayed (any
    value for model.anscombe_offset, which acted only with the Anscombe transform) it is read as today's config; at
    another value, or with a retired value, it is refused in one line naming the key, its value and the source."""
    saved = Config().to_dict()
    for key, retired in RETIRED.items():
        section, name = key.split(".")
        saved[section][name] = 0.02 if retired.remaining is EVERY_VALUE else retired.remaining
    assert config_from_dict(saved) == Config()
    for key, value in [("loss.lovasz_stride", 2), ("loss.class_balance", 0.5), ("data.unprocess", True),
                       ("model.decoder_join", "project"), ("model.input_transform", "anscombe"),
                       ("train.ema_decay", 0.999), RETIRED_VALUE, ("loss.distill_mode", "channel")]:
        section, name = key.split(".")
        asking = copy.deepcopy(saved)
        asking[section][name] = value
        with pytest.raises(ConfigError) as refused:
            config_from_dict(asking, "runs/old/config.json")
        message = str(refused.value)
        assert message.startswith(f"{key} = {value!r} was retired (") and "\n" not in message
        assert message.endswith("docs/records/history.md); runs/old/config.json asks for it: read that run with the "
                                "warpsense version that made it")
