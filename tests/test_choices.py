"""One source of truth per set of choices (warpsense.choices): the config, the CLI and the implementations agree."""

import dataclasses

import pytest

from warpsense import choices
from warpsense.camera.cfa import CFA, layout_letters
from warpsense.cli import build_parser
from warpsense.config import Config, ConfigError, load_config
from warpsense.data import DATASETS


def _config_choices() -> dict[str, tuple]:
    found = {}
    for section in dataclasses.fields(Config):
        for field in dataclasses.fields(getattr(Config(), section.name)):
            if "choices" in field.metadata:
                found[f"{section.name}.{field.name}"] = tuple(field.metadata["choices"])
    return found


def test_config_choices_are_the_shared_tuples():
    assert _config_choices() == {
        "run.device": choices.DEVICES, "data.dataset": choices.DATASETS, "data.on_device": choices.ON_DEVICE_MODES,
        "optics.method": choices.PSF_METHODS, "optics.render_precision": choices.RENDER_PRECISIONS,
        "cfa.pattern": tuple(choices.CFA_LAYOUTS),
        "cfa.mode": choices.CFA_MODES, "quantize.mode": choices.QUANTIZE_MODES, "train.compile": choices.COMPILE_MODES,
        "model.name": choices.MODEL_NAMES, "model.context": choices.MODEL_CONTEXTS, "model.input": choices.MODEL_INPUTS,
        "data.scale_fill": choices.SCALE_FILLS, "loss.distill_mode": choices.DISTILL_MODES,
        "photons.light": tuple(choices.LIGHT_LEVELS),
    }


def test_registries_implement_exactly_the_named_choices():
    from warpsense.models import MODELS

    assert set(DATASETS) == set(choices.DATASETS)
    assert set(MODELS) == set(choices.MODEL_NAMES)
    from warpsense.models.dsunet import CONTEXTS

    assert set(CONTEXTS) == set(choices.MODEL_CONTEXTS)
    from warpsense.train.losses import DISTILLATION

    assert set(DISTILLATION) == set(choices.DISTILL_MODES)
    for pattern in choices.CFA_LAYOUTS:
        assert len(layout_letters(pattern, 2)) == 2
    for mode in choices.CFA_MODES:
        CFA("RGGB", 2, mode)
    from warpsense.camera.cfa import FILTERS
    from warpsense.camera.photons import light_electrons

    assert "".join(FILTERS) == choices.CFA_FILTERS
    assert {name: light_electrons(name) for name in choices.LIGHT_LEVELS} == choices.LIGHT_LEVELS
    assert choices.BAYER_LAYOUTS == ("RGGB", "BGGR", "GRBG", "GBRG")
    assert set(choices.SELF_CAPTURING_COMPILE_MODES) < set(choices.COMPILE_MODES)
    from warpsense.data.transforms import check_fill

    for fill in choices.SCALE_FILLS:
        assert check_fill(fill) == fill
    with pytest.raises(KeyError, match="unknown scale fill 'zero'; valid: cover, reflect"):
        check_fill("zero")


def test_cli_offers_the_shared_choices():
    parser = build_parser()
    subcommands = next(a for a in parser._actions if a.dest == "command").choices
    options = {(name, action.dest): action.choices for name, sub in subcommands.items() for action in sub._actions
               if action.choices is not None}
    assert tuple(options[("eval", "data")]) == choices.DATASETS
    assert tuple(options[("eval", "device")]) == choices.DEVICES
    assert tuple(options[("predict", "device")]) == choices.DEVICES


def test_config_rejects_a_value_outside_the_choices_and_lists_them():
    with pytest.raises(ConfigError, match="patch"):
        load_config(None, ["optics.method=winograd"])
