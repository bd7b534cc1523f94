"""A stage is one unit: its config section is its constructor's signature, so a stage built in Python with its
constructor's defaults is the stage the default config builds (their defaults disagreed: CFA(temperature_end=1.0)
against cfa.temperature_end = 0.05, Exposure(gain_logit=0.0) against -1.3863, Optics(method="direct") against
"auto", PhotonBudget(mid_grey_electrons=70.0) against 0.0 and light = "night")."""

import dataclasses
import inspect

import pytest
import torch
from torch import nn

from warpsense.camera.camera import STAGES, Camera
from warpsense.camera.stage import SensorArguments
from warpsense.config import Config, load_config
from warpsense.train.schedule import Schedule

ALONGSIDE = {"photons": ["noise.enabled=false", "exposure.enabled=false"]}
"""What the default config needs besides a stage's own ``enabled`` to build it (`Stage.check_design`)."""


def _seeded(build):
    """``build()`` from the same random state (a noisy stage draws its training seed counter at construction)."""
    with torch.random.fork_rng():
        torch.manual_seed(0)
        return build()


def _from_default_config(name: str) -> nn.Module:
    stage = STAGES[name]
    config = load_config(None, [f"{stage.config_section}.enabled=true", *ALONGSIDE.get(name, [])])
    return getattr(_seeded(lambda: Camera.from_config(config)), name)


def _attributes(module: nn.Module) -> dict:
    """The stage's own plain attributes (settings such as a PSF method or a temperature plan)."""
    return {key: value for key, value in vars(module).items()
            if not key.startswith("_") and not isinstance(value, (torch.Tensor, nn.Module))}


def _assert_same_tensors(got: dict, expected: dict) -> None:
    assert got.keys() == expected.keys()
    for key in expected:
        assert got[key].dtype == expected[key].dtype, key
        assert torch.equal(got[key], expected[key]), key
        assert got[key].requires_grad == expected[key].requires_grad, key


def _assert_same_arguments(got: SensorArguments, expected: SensorArguments) -> None:
    for field in dataclasses.fields(SensorArguments):
        a, b = getattr(got, field.name), getattr(expected, field.name)
        if isinstance(b, torch.Tensor):
            assert torch.equal(a, b), field.name
        elif field.name != "seeds":  # a bound method of each stage
            assert a == b, field.name


@pytest.mark.parametrize("name", list(STAGES))
def test_constructor_takes_its_section_keys_with_their_defaults(name):
    """The constructor's keyword arguments are the section's keys but ``enabled``, with the section's defaults
    (the section's defaults are configs/default.toml's: tests/test_config.py)."""
    stage = STAGES[name]
    section = getattr(Config(), stage.config_section)
    keys = {key.name: getattr(section, key.name) for key in dataclasses.fields(section) if key.name != "enabled"}
    parameters = inspect.signature(stage).parameters
    assert {key: parameter.default for key, parameter in parameters.items()} == keys


@pytest.mark.parametrize("name", list(STAGES))
def test_a_stage_built_with_its_defaults_is_the_default_configs(name):
    """Same parameters, buffers and settings, the same fused-kernel arguments, and the same output on a fixed input,
    in eval and through a training plan (the CFA's temperature annealed to its end)."""
    configured = _from_default_config(name)
    built = _seeded(STAGES[name])
    assert type(built) is type(configured)
    _assert_same_tensors(dict(built.named_parameters()), dict(configured.named_parameters()))
    _assert_same_tensors(dict(built.named_buffers()), dict(configured.named_buffers()))
    assert _attributes(built) == _attributes(configured)

    channels = 3 if STAGES[name].takes == "rgb" else 1
    signal = torch.rand(2, channels, 8, 12, generator=torch.Generator().manual_seed(1))
    schedule = Schedule(epochs=4, warmup_epochs=1)
    for epoch in (None, *range(schedule.epochs)):
        for stage in (built, configured):
            if epoch is not None:
                stage.on_epoch(schedule, epoch)
            stage.eval()
        if STAGES[name].part == "sensor":
            fused = [SensorArguments(torch.full((1, 1, 3), 1 / 3)) for _ in range(2)]
            assert built.fuse(fused[0]) == configured.fuse(fused[1])
            _assert_same_arguments(fused[0], fused[1])
        assert built.summary() == configured.summary()
        with torch.no_grad():
            assert torch.equal(built(signal), configured(signal))
