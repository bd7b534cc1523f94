"""`Camera.cached`: inference with a fixed camera reuses the sensor kernel's arguments, and gives what the camera
gives without it."""

import pytest
import torch
from torch import nn

from warpsense.camera import Camera
from warpsense.camera.camera import cached_cameras
from warpsense.config import load_config


def _camera(*overrides: str) -> Camera:
    torch.manual_seed(0)
    return Camera.from_config(load_config(None, ["cfa.mode=softmax", "noise.learnable=true", *overrides])).eval()


def _count_arguments(camera: Camera, monkeypatch) -> list:
    calls = []
    original = camera.sensor_arguments

    def counted():
        calls.append(1)
        return original()

    monkeypatch.setattr(camera, "sensor_arguments", counted)
    return calls


def test_feature_cached_equals_uncached_with_and_without_image_index(monkeypatch):
    camera = _camera("optics.enabled=true")
    radiance = torch.rand(2, 3, 8, 10)
    index = torch.tensor([5, 9])
    with torch.no_grad():
        expected, expected_indexed = camera(radiance), camera(radiance, index)
        calls = _count_arguments(camera, monkeypatch)
        with camera.cached():
            for _ in range(2):
                torch.testing.assert_close(camera(radiance), expected, rtol=0, atol=0)
                torch.testing.assert_close(camera(radiance, index), expected_indexed, rtol=0, atol=0)
            torch.testing.assert_close(camera(radiance[:1]), expected[:1], rtol=0, atol=0)  # seeds per batch size
        assert len(calls) == 1  # computed once for the five calls
        assert camera._cache is None
        camera(radiance)
        assert len(calls) == 2  # outside: computed every call


def test_feature_cached_notices_in_place_changes_and_what_if_overrides():
    camera, fresh = _camera(), _camera()
    radiance = torch.rand(1, 3, 6, 8)
    with torch.no_grad(), camera.cached():
        first = camera(radiance)
        camera.exposure.gain_logit.add_(0.7)  # an optimizer step or load_state_dict changes tensors in place
        fresh.exposure.gain_logit.add_(0.7)
        changed = camera(radiance)
        assert not torch.equal(changed, first)
        torch.testing.assert_close(changed, fresh(radiance), rtol=0, atol=0)
        fresh.load_state_dict(_camera().state_dict())
        camera.load_state_dict(_camera().state_dict())
        torch.testing.assert_close(camera(radiance), first, rtol=0, atol=0)
        with camera.overridden(noise_scale=3.0), fresh.overridden(noise_scale=3.0):
            torch.testing.assert_close(camera(radiance), fresh(radiance), rtol=0, atol=0)
        torch.testing.assert_close(camera(radiance), first, rtol=0, atol=0)


def test_feature_training_and_gradients_bypass_the_cache(monkeypatch):
    camera = _camera()
    radiance = torch.rand(1, 3, 6, 8)
    calls = _count_arguments(camera, monkeypatch)
    with camera.cached():
        with torch.no_grad():
            camera(radiance)
        raw = camera(radiance)  # eval with gradients: computed, and differentiable
        (grad,) = torch.autograd.grad(raw.sum(), [camera.noise.shot_logit])
        assert torch.isfinite(grad).all() and grad.abs().sum() > 0
        camera.train()
        with torch.no_grad():
            camera(radiance)
            camera(radiance)
    assert len(calls) == 4


def test_module_cached_cameras_nests_and_drops_on_exit():
    system = nn.Sequential(_camera(), nn.Identity())
    camera = system[0]
    with cached_cameras(system) as inside:
        assert inside is system and camera._cache == {}
        with camera.cached():
            with torch.no_grad():
                camera(torch.rand(1, 3, 4, 4))
        assert camera._cache  # the inner exit keeps the outer context's cache
    assert camera._cache is None


def test_exception_cached_is_dropped_when_the_block_raises():
    camera = _camera()
    with pytest.raises(RuntimeError, match="inside"):
        with camera.cached():
            raise RuntimeError("inside")
    assert camera._cache is None


def test_feature_jit_trace_inside_cached_records_the_computation():
    """torch.jit.trace inside `cached` traces the arguments' computation, not the cached tensors as constants: the
    traced camera follows a later change of a parameter."""
    camera = _camera("optics.enabled=true", "optics.method=direct")
    radiance = torch.rand(1, 3, 8, 10)
    with torch.no_grad(), camera.cached():
        camera(radiance)  # fills the cache
        traced = torch.jit.trace(camera, radiance, check_trace=False)
        camera.noise.read_logit.add_(1.0)
        camera.cfa.logits.mul_(3.0)
        expected = camera(radiance)
        torch.testing.assert_close(traced(radiance), expected)
