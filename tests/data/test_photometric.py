"""RadianceJitter: photometric augmentation of the linear radiance before the camera (training only)."""

import math

import pytest
import torch

from warpsense.config import load_config
from warpsense.data.photometric import RadianceJitter


def _radiance(batch=64, height=9, width=13):
    torch.manual_seed(0)
    return torch.rand(batch, 3, height, width) * 0.9 + 0.05


def test_smoke_off_is_none_and_on_keeps_shape():
    assert RadianceJitter.from_config(load_config(None).data) is None  # the default costs nothing
    config = load_config(None, ["data.jitter_stops=1.0", "data.jitter_vignetting=0.5"])
    jitter = RadianceJitter.from_config(config.data)
    assert (jitter.stops, jitter.gamma, jitter.white_balance, jitter.vignetting) == (1.0, 0.0, 0.0, 0.5)
    radiance = _radiance()
    out = jitter(radiance)
    assert out.shape == radiance.shape and out.dtype == radiance.dtype and bool((out >= 0).all())


@pytest.mark.parametrize("key,value", [("stops", -0.1), ("gamma", 11.0), ("white_balance", 3.0),
                                       ("vignetting", 1.5)])
def test_exception_out_of_range(key, value):
    with pytest.raises(ValueError, match=f"data.jitter_{key}"):
        RadianceJitter(**{key: value})
    with pytest.raises(Exception, match=f"jitter_{key}"):
        load_config(None, [f"data.jitter_{key}={value}"])


def test_exception_shape():
    with pytest.raises(ValueError, match=r"\[B, 3, H, W\]"):
        RadianceJitter(stops=1.0)(torch.rand(2, 1, 4, 4))


def test_feature_exposure_is_a_per_image_gain_within_its_stops():
    radiance = _radiance()
    out = RadianceJitter(stops=1.5)(radiance)
    ratio = out / radiance  # one gain per image, the same at every pixel and channel
    per_image = ratio.flatten(1)
    torch.testing.assert_close(per_image, per_image[:, :1].expand_as(per_image))
    stops = torch.log2(per_image[:, 0])
    assert bool((stops.abs() <= 1.5 + 1e-5).all())
    assert stops.min() < -0.75 and stops.max() > 0.75  # 64 draws spread over the range


def test_feature_gamma_keeps_black_and_white_and_is_a_power():
    radiance = _radiance()
    radiance[:, :, 0, 0], radiance[:, :, 0, 1] = 0.0, 1.0
    out = RadianceJitter(gamma=1.0)(radiance)
    assert bool((out[:, :, 0, 0] == 0).all()) and torch.allclose(out[:, :, 0, 1], torch.ones(64, 3))
    exponent = torch.log(out[:, :, 1:, :]) / torch.log(radiance[:, :, 1:, :])  # one exponent per image
    flat = exponent.flatten(1)
    torch.testing.assert_close(flat, flat[:, :1].expand_as(flat), rtol=1e-4, atol=1e-4)
    assert bool((flat[:, 0] <= 2 + 1e-4).all() and (flat[:, 0] >= 0.5 - 1e-4).all())


def test_feature_white_balance_scales_red_and_blue_not_green():
    radiance = _radiance()
    out = RadianceJitter(white_balance=0.3)(radiance)
    torch.testing.assert_close(out[:, 1], radiance[:, 1])
    gains = (out[:, [0, 2]] / radiance[:, [0, 2]]).flatten(2)
    assert bool((gains.log().abs() <= 0.3 + 1e-5).all())
    assert not torch.allclose(gains[:, 0], gains[:, 1])  # red and blue drawn independently


def test_feature_vignetting_against_numpy_reference():
    import numpy as np

    radiance = torch.ones(32, 3, 7, 11)
    out = RadianceJitter(vignetting=0.8)(radiance)
    torch.testing.assert_close(out[:, :, 3, 5], torch.ones(32, 3))  # the centre keeps its light
    y, x = np.meshgrid(np.linspace(-3.5, 3.5, 7), np.linspace(-5.5, 5.5, 11), indexing="ij")
    r2 = (y**2 + x**2) / (3.5**2 + 5.5**2)
    for image in out:  # 1 - a r^2 for one a per image, a in [0, 0.8]
        a = (1 - float(image[0, 0, 0])) / r2[0, 0]
        assert -1e-6 <= a <= 0.8 + 1e-6
        np.testing.assert_allclose(image[1].numpy(), 1 - a * r2, rtol=1e-5, atol=1e-6)


def test_feature_draws_follow_torch_seed():
    radiance = _radiance()
    jitter = RadianceJitter(stops=1.0, gamma=0.5, white_balance=0.2, vignetting=0.3)
    torch.manual_seed(5)
    first = jitter(radiance)
    torch.manual_seed(5)
    assert torch.equal(first, jitter(radiance))
    assert not torch.equal(first, jitter(radiance))


def test_module_the_training_step_jitters_the_scene_and_eval_does_not(monkeypatch):
    """The step hands the camera the jittered linear radiance of the batch's uint8 frames; evaluation (the model
    alone) never sees the jitter."""
    from warpsense.data.color import srgb_to_linear
    from warpsense.system import build_system
    from warpsense.train.step import TrainingStep

    config = load_config(None, ["noise.enabled=false", "data.jitter_stops=1.0"])
    torch.manual_seed(0)
    model = build_system(config, 11)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    jitter = RadianceJitter.from_config(config.data)
    step = TrainingStep(config.loss, optimizer, model.camera.learnable_parameters(), 4, False, radiance_jitter=jitter)
    images = torch.randint(0, 256, (2, 3, 16, 24), dtype=torch.uint8)
    labels = torch.randint(0, 11, (2, 16, 24))
    seen = []
    original = model.camera.forward
    monkeypatch.setattr(model.camera, "forward", lambda radiance, index=None: seen.append(radiance) or
                        original(radiance, index))
    step(model, images, labels, 0, joint=False)
    ratio = (seen[0] / srgb_to_linear(images)).flatten(1)
    finite = ratio[:, torch.isfinite(ratio).all(0)]
    torch.testing.assert_close(finite, finite[:, :1].expand_as(finite))  # an exposure per image
    assert not torch.allclose(finite[:, 0], torch.ones(2))
    model.eval()
    with torch.no_grad():
        model(images)
    torch.testing.assert_close(seen[-1], srgb_to_linear(images))
    assert math.isfinite(float(step.totals["loss"]))
