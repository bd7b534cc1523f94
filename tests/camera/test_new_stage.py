"""The README's recipe for a new stage, followed to the letter by a stage defined only here (a kernel-free pixel gain):
a Stage subclass, its config section (a dataclass on the config), and one line in STAGES. It runs in the camera
fused (placed before the noise, it folds into the responses) or not (after the noise it cannot be fused, and turns
fusing off instead of being skipped)."""

import dataclasses
import re
from dataclasses import dataclass, field

import pytest
import torch
from torch import nn

from warpsense.camera import Camera
from warpsense.camera import camera as camera_module
from warpsense.camera.stage import SensorArguments, Stage
from warpsense.config import Config, ConfigError, load_config
from warpsense.ops import cfa_mosaic, poisson_gaussian, quantize_ste


@dataclass
class PixelGainConfig:
    enabled: bool = True
    gain: float = 1.7


class PixelGain(Stage):
    """RAW -> gain * RAW, a learnable analog gain."""

    config_section = "pixel_gain"

    def __init__(self, gain: float):
        super().__init__()
        self.gain = nn.Parameter(torch.tensor(float(gain)))

    @classmethod
    def from_config(cls, section) -> "PixelGain":
        return cls(section.gain)

    def fuse(self, arguments: SensorArguments) -> bool:
        if arguments.noisy or arguments.bits is not None:
            return False  # a gain after the noise (or the ADC) does not commute with it
        arguments.multiply_gain(self.gain)
        return True

    def forward(self, raw, image_index=None):
        return raw * self.gain

    def summary(self) -> dict:
        return {"pixel_gain": float(self.gain.detach())}


ConfigWithGain = dataclasses.make_dataclass(
    "ConfigWithGain", [("pixel_gain", PixelGainConfig, field(default_factory=PixelGainConfig))], bases=(Config,))


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
