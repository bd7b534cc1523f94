"""The recipe for a new stage (docs/guide/development.md, "Adding a stage"), followed by a stage defined only here,
a pixel gain: its kernel, its op, its stage with its config section, and its registration (the section on the
config, one line in STAGES). It runs in the camera fused (placed before the noise, it folds into the responses) or
not (after the noise it cannot be fused, turns fusing off instead of being skipped, and runs its own op)."""

import dataclasses
import re
from dataclasses import dataclass, field

import pytest
import torch
import warp as wp
from torch import nn

from warpsense.camera import Camera
from warpsense.camera import camera as camera_module
from warpsense.camera.stage import SensorArguments, Stage
from warpsense.config import Config, ConfigError, _field, load_config
from warpsense.ops import cfa_mosaic, poisson_gaussian, quantize_ste
from warpsense.ops._warp import launch, prepare, save_inputs, warp_op

# 1. the kernel (kernels/<stage>.py): forward and an explicit backward, no torch

wp.set_module_options({"enable_backward": False})


@wp.kernel
def gain_forward(raw: wp.array2d(dtype=wp.float32), gain: wp.array(dtype=wp.float32),
                 out: wp.array2d(dtype=wp.float32)):
    b, i = wp.tid()
    out[b, i] = gain[0] * raw[b, i]


@wp.kernel
def gain_backward(raw: wp.array2d(dtype=wp.float32), gain: wp.array(dtype=wp.float32),
                  grad_out: wp.array2d(dtype=wp.float32), grad_raw: wp.array2d(dtype=wp.float32),
                  grad_gain: wp.array(dtype=wp.float32)):
    b, i = wp.tid()
    grad_raw[b, i] = gain[0] * grad_out[b, i]
    wp.atomic_add(grad_gain, 0, raw[b, i] * grad_out[b, i])


# 2. the op (warpsense/ops/<stage>.py): the kernels as a torch custom op with its autograd formula


@warp_op("test_pixel_gain_backward", lambda rows, gain, grad_out: (torch.empty_like(rows), torch.empty_like(gain)))
def _pixel_gain_backward(rows: torch.Tensor, gain: torch.Tensor,
                         grad_out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    grad_rows, grad_gain = torch.empty_like(rows), torch.zeros_like(gain)
    launch(gain_backward, tuple(rows.shape), [rows, gain, grad_out.contiguous(), grad_rows, grad_gain], rows.device)
    return grad_rows, grad_gain


def _backward(ctx, grad_out):
    return _pixel_gain_backward(*ctx.saved_tensors, grad_out)


@warp_op("test_pixel_gain", lambda rows, gain: torch.empty_like(rows), _backward, save_inputs)
def _pixel_gain(rows: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:
    out = torch.empty_like(rows)
    launch(gain_forward, tuple(rows.shape), [rows, gain, out], rows.device)
    return out


def pixel_gain(raw: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:
    """RAW [B, 1, H, W] (float32) times a 0-d gain."""
    rows, gain = prepare(raw.reshape(raw.shape[0], -1), gain.reshape(1))
    return _pixel_gain(rows, gain).view(raw.shape)


# 3. the stage (warpsense/camera/<stage>.py) and its config section (warpsense/config.py): the section's keys but
# `enabled` are the constructor's arguments, its defaults the constructor's; `Stage.from_config` is inherited


@dataclass
class PixelGainConfig:
    enabled: bool = True
    gain: float = _field(1.7, minimum=0)


class PixelGain(Stage):
    """RAW -> gain * RAW, a learnable analog gain."""

    config_section = "pixel_gain"

    def __init__(self, gain: float = PixelGainConfig.gain):
        super().__init__()
        self.gain = nn.Parameter(torch.tensor(float(gain)))

    def fuse(self, arguments: SensorArguments) -> bool:
        if arguments.noisy or arguments.bits is not None:
            return False  # a gain after the noise (or the ADC) does not commute with it
        arguments.multiply_gain(self.gain)
        return True

    def forward(self, raw, image_index=None):
        return pixel_gain(raw, self.gain)

    def summary(self) -> dict:
        return {"pixel_gain": float(self.gain.detach())}


# 4. the registration: the section a field of Config (and its lines in configs/default.toml), one line in STAGES

ConfigWithGain = dataclasses.make_dataclass(
    "ConfigWithGain", [("pixel_gain", PixelGainConfig, field(default_factory=PixelGainConfig))], bases=(Config,))


def test_the_op_equals_its_torch_form_forward_and_backward():
    raw = torch.rand(2, 1, 5, 7, requires_grad=True)
    gain = torch.tensor(1.7, requires_grad=True)
    out = pixel_gain(raw, gain)
    torch.testing.assert_close(out, raw * 1.7, atol=0, rtol=0)
    weights = torch.rand(2, 1, 5, 7)
    grad_raw, grad_gain = torch.autograd.grad((out * weights).sum(), (raw, gain))
    torch.testing.assert_close(grad_raw, weights * 1.7)
    torch.testing.assert_close(grad_gain, (raw * weights).sum().detach())


def _plugged(monkeypatch, after: str) -> Camera:
    """The camera of the default config with the gain stage inserted after ``after`` in STAGES."""
    stages = {}
    for name, stage in camera_module.STAGES.items():
        stages[name] = stage
        if name == after:
            stages["pixel_gain"] = PixelGain  # the one line in STAGES
    monkeypatch.setattr(camera_module, "STAGES", stages)
    config = ConfigWithGain(**{f.name: getattr(load_config(None), f.name) for f in dataclasses.fields(Config)})
    return Camera.from_config(config).eval()


def test_a_stage_before_the_noise_is_fused_and_equals_brighter_radiance(monkeypatch):
    base = Camera.from_config(load_config(None)).eval()
    camera = _plugged(monkeypatch, after="cfa")
    assert [name for name, _ in camera.stages()] == ["exposure", "cfa", "pixel_gain", "noise", "quantizer"]
    assert camera.fusable()
    assert camera.summary()["pixel_gain"] == pytest.approx(1.7)
    assert torch.equal(camera.pixel_gain.gain, PixelGain().gain)  # the default config's is the default stage
    radiance = torch.rand(2, 3, 6, 8)
    raw = camera(radiance)
    # the gain before the noise is the same capture as 1.7x the light (same eval noise seeds)
    torch.testing.assert_close(raw, base(radiance * 1.7), atol=2 / 1023, rtol=0)
    camera.train()
    camera(radiance).sum().backward()
    assert camera.pixel_gain.gain.grad is not None and camera.pixel_gain.gain.grad != 0


def test_a_stage_that_cannot_be_fused_turns_fusing_off_and_still_runs(monkeypatch):
    camera = _plugged(monkeypatch, after="noise")
    assert [name for name, _ in camera.stages()] == ["exposure", "cfa", "noise", "pixel_gain", "quantizer"]
    assert not camera.fusable()
    radiance = torch.rand(2, 3, 6, 8)
    raw = camera(radiance)
    # the reference chain from the ops alone: the gain acts on the noisy signal, before the ADC
    config = load_config(None)
    shot, read = config.noise.shot, config.noise.read
    seeds = config.noise.eval_seed + torch.arange(2)
    phi = camera.responses().detach()
    expected = quantize_ste(poisson_gaussian(cfa_mosaic(radiance, phi), shot, read, seeds) * 1.7,
                            config.quantize.bits)
    torch.testing.assert_close(raw, expected, atol=1e-6, rtol=0)
    raw.sum().backward()
    assert camera.pixel_gain.gain.grad is not None and camera.pixel_gain.gain.grad != 0


def test_what_if_overrides_go_through_the_camera_and_are_restored():
    camera = Camera.from_config(load_config(None)).eval()
    assert camera.what_if_values() == {"noise_scale": 1.0, "exact_noise": False, "bits": 10}
    radiance = torch.rand(2, 3, 6, 8)
    before = camera(radiance)
    noiseless = Camera.from_config(load_config(None, ["noise.enabled=false"])).eval()
    with camera.overridden(noise_scale=0.0):
        torch.testing.assert_close(camera(radiance), noiseless(radiance), atol=0, rtol=0)
    with camera.overridden(bits=4):
        codes = camera(radiance) * 15
        torch.testing.assert_close(codes, codes.round(), atol=1e-5, rtol=0)
    with camera.overridden(exact_noise=True):
        assert not camera.fusable()  # exact Poisson counts take the noise stage's own op
        assert not torch.equal(camera(radiance), before)
    assert camera.fusable() and camera.what_if_values()["bits"] == 10
    assert torch.equal(camera(radiance), before)
    with pytest.raises(KeyError, match="gamma not accepted by this camera; accepted: noise_scale, exact_noise, bits"):
        with camera.overridden(gamma=2.0):
            pass
    assert camera.what_if_values() == {"noise_scale": 1.0, "exact_noise": False, "bits": 10}
    # values a stage cannot run with are refused by that stage before any is set (a negative noise scale ran)
    # bits is the config's quantize.bits: the config checks it, with its own message (warpsense.config.check_value)
    for values, message in (({"bits": 8, "noise_scale": -1.0}, "noise_scale: must be a finite number >= 0, got -1.0"),
                            ({"noise_scale": float("nan")}, "noise_scale: must be a finite number >= 0, got nan"),
                            ({"bits": 0}, "quantize.bits: must be >= 1, got 0"),
                            ({"bits": 25}, "quantize.bits: must be <= 24, got 25"),
                            ({"bits": 8.0}, "quantize.bits: expected int, got float 8.0"),
                            ({"exact_noise": 1}, "exact_noise: expected bool, got int 1")):
        with pytest.raises(ValueError, match=rf"^Camera\.overridden: {re.escape(message)}$"):
            with camera.overridden(**values):
                pass
        assert camera.what_if_values() == {"noise_scale": 1.0, "exact_noise": False, "bits": 10}
    with pytest.raises(ConfigError) as refused:
        with camera.overridden(bits=30):
            pass
    with pytest.raises(ConfigError) as loaded:
        load_config(None, ["quantize.bits=30"])
    assert str(refused.value).split(": ", 1)[1] == str(loaded.value).split(": ", 1)[1]  # the loader's words
