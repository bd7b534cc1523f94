import dataclasses
import json
import sys

import pytest

from warpsense.config import CONFIG_DIR, Config, ConfigError, load_config, parse_override, preset_names

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
    config = load_config("camvid_ablation_no_optics", ["train.epochs=3", "data.hflip=false", "optics.lens=phone_80deg"])
    assert config.data.dataset == "camvid"  # from the base preset
    assert config.optics.enabled is False  # the ablation's own change
    assert config.train.epochs == 3 and config.data.hflip is False and config.optics.lens == "phone_80deg"


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
    bad.write_text("[noise\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="no such file or preset"):
        load_config("nope")


def test_int_accepted_for_float_and_save_round_trip(tmp_path):
    config = load_config(None, ["noise.shot=1", "run.name=\"x y\""])
    assert config.noise.shot == 1.0 and isinstance(config.noise.shot, float)
    config.save(tmp_path / "config.json")
    saved = json.loads((tmp_path / "config.json").read_text())
    assert saved["run"]["name"] == "x y"
    from warpsense.config import config_from_dict

    assert dataclasses.asdict(config_from_dict(saved)) == dataclasses.asdict(config)
