"""Bounded camera parameters started on their bounds (issue 61): each starts at each bound, passes the config checks,
and takes an optimizer step on the CPU with finite gradients and finite parameters; a start outside its bounds is
one config error naming the key."""

import math

import pytest
import torch

from warpsense.camera import Camera
from warpsense.camera.bounds import BOUND_MARGIN, FIXED_LOGIT, log_bounded, log_bounded_parameter
from warpsense.camera.exposure import Exposure
from warpsense.camera.noise import SensorNoise
from warpsense.camera.optics import Optics
from warpsense.config import ConfigError, load_config
from warpsense.system import check_config
from warpsense.train.engine import train

PHOTONS = ["photons.enabled=true", "noise.enabled=false", "exposure.enabled=false"]
OPTICS = ["optics.enabled=true", "optics.normalize_mean=0.0"]
F_NUMBER = [*OPTICS, "optics.f_number_learnable=true"]
EXPOSURE_MS = [*OPTICS, "optics.exposure_learnable=true", "optics.corner_speed_px_per_ms=0.3"]  # with its streaks
GAIN = [*PHOTONS, "photons.gain_learnable=true"]


def _f_number(camera):
    return camera.optics.f_number()


def _exposure_ms(camera):
    return camera.optics.exposure_ms()


def _gain(camera):
    return camera.photons.analog_gain()


# (overrides, learnable parameter, its value, the bound it starts on, the other bound)
ON_A_BOUND = {
    "f_number_min": (F_NUMBER + ["optics.f_number=1.4"], "optics.f_number_logit", _f_number, 1.4, 8.0),
    "f_number_max": (F_NUMBER + ["optics.f_number=8.0"], "optics.f_number_logit", _f_number, 8.0, 1.4),
    # optics.f_number = 0 starts at the lens file's f/1.9, here the lower bound
    "f_number_lens_file_min": (F_NUMBER + ["optics.f_number_min=1.9"], "optics.f_number_logit", _f_number, 1.9, 8.0),
    "exposure_ms_min": (EXPOSURE_MS + ["optics.exposure_ms=1.0"], "optics.exposure_logit", _exposure_ms, 1.0, 30.0),
    "exposure_ms_max": (EXPOSURE_MS + ["optics.exposure_ms=30.0"], "optics.exposure_logit", _exposure_ms, 30.0, 1.0),
    "analog_gain_min_default": (GAIN, "photons.gain_logit", _gain, 1.0, 64.0),
    "analog_gain_max": (GAIN + ["photons.analog_gain=64.0"], "photons.gain_logit", _gain, 64.0, 1.0),
    "analog_gain_max_read_free": (GAIN + ["photons.analog_gain=8.0", "photons.gain_max=8.0",
                                          "photons.read_electrons=0.0"], "photons.gain_logit", _gain, 8.0, 1.0),
}


def _camera(overrides) -> Camera:
    config = load_config(None, overrides)
    check_config(config)  # what `warpsense train` checks first
    camera = Camera.from_config(config).train()
    if camera.optics is not None:
        camera.optics.lens.spec.pupil_samples = 16  # a coarse pupil keeps the CPU rendering fast
    return camera


def _one_step(camera: Camera) -> dict[str, torch.Tensor]:
    """One AdamW step of the learnable camera parameters on a tiny frame; the gradients it took, by name."""
    learnable = [p for p in camera.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(learnable, lr=1e-2, weight_decay=0.0)
    torch.manual_seed(0)
    raw = camera(torch.rand(2, 3, 16, 16))
    raw.square().mean().backward()
    grads = {name: p.grad.clone() for name, p in camera.named_parameters() if p.grad is not None}
    optimizer.step()
    for name, parameter in camera.named_parameters():
        assert torch.isfinite(parameter).all(), f"{name} is not finite after one step"
    for name, grad in grads.items():
        assert torch.isfinite(grad).all(), f"{name}'s gradient is not finite"
    return grads


@pytest.mark.parametrize("case", list(ON_A_BOUND))
def test_a_learnable_start_on_a_bound_trains_from_just_inside_it(case):
    overrides, name, value, bound, other = ON_A_BOUND[case]
    camera = _camera(overrides)
    start = float(value(camera).detach())
    # BOUND_MARGIN of the log range inside the bound, towards the other one
    expected = bound * (other / bound) ** BOUND_MARGIN
    assert start == pytest.approx(expected, rel=1e-5)
    assert min(bound, other) < start < max(bound, other)
    grads = _one_step(camera)
    # the parameter can leave the bound: its gradient is not zero
    assert float(grads[name].abs()) > 0, f"{name} took no gradient on its bound"
    moved = float(value(camera).detach())
    assert math.isfinite(moved) and min(bound, other) <= moved <= max(bound, other)


@pytest.mark.parametrize("gain", [1.0, 64.0])
def test_a_fixed_gain_on_a_bound_is_exact_and_finite(gain):
    # analog_gain = 1 is the default: every photon-budget run with a fixed gain starts here
    camera = _camera([*PHOTONS, f"photons.analog_gain={gain}"])
    logit = camera.photons.gain_logit
    assert torch.isfinite(logit) and abs(float(logit)) == FIXED_LOGIT and not logit.requires_grad
    assert float(camera.photons.analog_gain()) == gain
    assert float(camera.photons.double().analog_gain()) == gain
    _one_step(camera.float())


@pytest.mark.parametrize("overrides", [
    ["noise.learnable=true", "noise.shot=0.0"],  # the levels' lower bound of [0, 2 x start]
    ["noise.learnable=true", "noise.read=0.0"],
    ["noise.learnable=true", "noise.shot=0.0", "noise.read=0.0"],
    ["noise.learnable=true", "noise.shot=0.0", "noise.read=0.0", "quantize.enabled=false"],
    ["exposure.gain_logit=30.0"],  # a(g) = 4 in float32: the gain's upper bound
    ["exposure.gain_logit=-30.0"],  # a(g) = 0.25
], ids=["shot_0", "read_0", "both_0", "both_0_unquantized", "exposure_gain_max", "exposure_gain_min"])
def test_noise_levels_and_exposure_gain_on_their_bounds_take_a_finite_step(overrides):
    camera = _camera(overrides)
    if camera.exposure is not None and "exposure.gain_logit" in overrides[0]:
        assert float(camera.exposure.gain().detach()) in (0.25, 4.0)
    grads = _one_step(camera)
    learnable = [name for name, p in camera.named_parameters() if p.requires_grad]
    assert ("noise.shot_logit" in learnable) == ("noise.learnable=true" in overrides)
    assert set(learnable) <= set(grads)


def test_an_infinite_start_is_refused_naming_the_key():
    with pytest.raises(ValueError, match=r"^exposure.gain_logit must be finite, got inf$"):
        Exposure(gain_logit=math.inf)
    with pytest.raises(ValueError, match=r"^noise.shot and noise.read must be finite"):
        SensorNoise(shot=math.inf)
    with pytest.raises(ConfigError, match=r"exposure.gain_logit: must be finite"):
        load_config(None, ["exposure.gain_logit=inf"])


@pytest.mark.parametrize("overrides, message", [
    (F_NUMBER + ["optics.f_number=1.2"], r"optics.f_number = 1.2 must lie within \[optics.f_number_min, "
                                         r"optics.f_number_max\] = \[1.4, 8.0\] \(optics.f_number_learnable = true\)"),
    (F_NUMBER + ["optics.f_number_min=2.0"], r"optics.f_number \(0: the lens file's\) = 1.9 must lie within"),
    (F_NUMBER + ["optics.f_number=2.0", "optics.f_number_min=2.0", "optics.f_number_max=2.0"],
     r"optics.f_number is learned within \[optics.f_number_min, optics.f_number_max\] = \[2.0, 2.0\]: the bounds "
     r"must satisfy 0 < low < high"),
    (EXPOSURE_MS + ["optics.exposure_ms=31.0"], r"optics.exposure_ms = 31.0 must lie within \[optics.exposure_ms_min"),
    (EXPOSURE_MS + ["optics.exposure_ms_min=20.0", "optics.exposure_ms_max=5.0"],
     r"optics.exposure_ms_min \(20.0\) must be <= optics.exposure_ms_max \(5.0\)"),
    (GAIN + ["photons.analog_gain=65.0"], r"photons.analog_gain = 65.0 must lie within \[1, photons.gain_max\] = "
                                          r"\[1.0, 64.0\]"),
    ([*PHOTONS, "photons.analog_gain=65.0"], r"photons.analog_gain = 65.0 must lie within"),  # fixed, too
])
def test_a_start_outside_its_bounds_is_one_config_error_naming_the_key(overrides, message):
    with pytest.raises(ConfigError, match=message) as error:
        check_config(load_config(None, overrides))
    assert "\n" not in str(error.value)


def test_the_stage_constructors_refuse_what_the_config_check_refuses():
    config = load_config(None, F_NUMBER + ["optics.f_number=9.0"])
    with pytest.raises(ValueError, match=r"^optics.f_number = 9.0 must lie within \[optics.f_number_min"):
        Optics.from_config(config.optics)  # the stage alone (Camera.from_config runs the config check first)
    with pytest.raises(ValueError, match=r"^Camera.from_config: optics.f_number = 9.0 must lie within"):
        Camera.from_config(config)
    with pytest.raises(ValueError, match=r"^photons.analog_gain = 0.5 must lie within \[1, photons.gain_max\]"):
        log_bounded_parameter(0.5, 1.0, 64.0, key="photons.analog_gain", bound_keys=("1", "photons.gain_max"))


@pytest.mark.parametrize("value, low, high", [(1.4, 1.4, 8.0), (8.0, 1.4, 8.0), (1.0, 1.0, 64.0), (64.0, 1.0, 64.0)])
def test_the_stored_logit_is_finite_on_both_bounds_learnable_or_not(value, low, high):
    learned = log_bounded_parameter(value, low, high, learnable=True)
    fixed = log_bounded_parameter(value, low, high, learnable=False)
    assert torch.isfinite(learned) and torch.isfinite(fixed)
    # exactly the bound, in float32 (as float32 holds it) and in float64
    assert float(log_bounded(fixed.detach(), low, high)) == float(torch.tensor(value, dtype=torch.float32))
    assert float(log_bounded(fixed.detach().double(), low, high)) == value
    assert float(log_bounded(learned.detach().double(), low, high)) != value


TINY_RUN = ["data.scenes_train=4", "data.scenes_val=2", "data.batch_size=2", "data.scene_height=16",
            "data.scene_width=16", "data.crop_height=16", "data.crop_width=16", "model.width=4", "train.epochs=1",
            "train.warmup_epochs=0", "train.max_steps_per_epoch=1", "train.plots=false", "train.amp=false"]


@pytest.mark.parametrize("overrides", [
    PHOTONS,  # the defaults: a fixed unity analog gain
    [*PHOTONS, *OPTICS, "optics.f_number_learnable=true", "optics.f_number=1.4", "optics.exposure_learnable=true",
     "optics.exposure_ms=30.0", "photons.gain_learnable=true"],
], ids=["fixed_unity_gain", "learned_on_bounds"])
def test_a_run_started_on_the_bounds_trains_and_saves(tmp_path, overrides):
    run = train(load_config(None, [*TINY_RUN, *overrides, f"run.output_dir={tmp_path}"]), progress=False)
    assert (run / "checkpoint_last.safetensors").is_file()
