"""Regression tests for the numerics audit (issue 15): D1 exact Poisson, D2 white level, D3 code flips, D9 double
backward, D11 max mode, and input policies."""

import pytest
import torch

from warpsense.ops import cfa_mosaic, poisson_gaussian, poisson_gaussian_exact, psf_conv, quantize_ste
from warpsense.ops.noise import POISSON_NORMAL_LIMIT
from warpsense.ops.reference import quantize_reference
from warpsense.ops.sensor import sensor_capture


@pytest.mark.parametrize("mean_count", [50.0, 1e6, 1e8, 1e9])
def test_exact_poisson_mean_and_variance_at_every_count(mean_count):
    shot = 1e-3
    raw = torch.full((1, 200_000), mean_count * shot, dtype=torch.float64)
    counts = poisson_gaussian_exact(raw, shot, 0.0, 5) / shot
    assert counts.mean().item() == pytest.approx(mean_count, rel=5e-3 / mean_count**0.5 * 10 + 1e-6)
    assert counts.var().item() == pytest.approx(mean_count, rel=0.02)
    assert (counts >= 0).all() and torch.equal(counts, counts.round())
    if mean_count > POISSON_NORMAL_LIMIT:
        assert counts.max().item() < 2**33  # no uint32 wrap


def test_exact_poisson_passes_non_finite_through():
    raw = torch.tensor([[float("nan"), float("inf"), 0.5]])
    out = poisson_gaussian_exact(raw, 0.01, 0.0, 1)
    assert out[0, 0].isnan() and out[0, 1] == float("inf") and torch.isfinite(out[0, 2])


@pytest.mark.parametrize("white", [float("inf"), 1e-46, 1e39, float("nan"), 0.0, -1.0])
def test_white_level_outside_float32_rejected(white):
    with pytest.raises(ValueError, match="white_level"):
        quantize_ste(torch.rand(1, 4), 10, white)


def _near_thresholds(bits: int, count: int = 20_000) -> torch.Tensor:
    """float32 values within a few ulps of code thresholds (k + 1/2) / L: where float32 arithmetic flips codes."""
    generator = torch.Generator().manual_seed(bits)
    levels = (1 << bits) - 1
    codes = torch.randint(0, levels, (count,), generator=generator, dtype=torch.float64)
    values = ((codes + 0.5) / levels).float()
    steps = torch.randint(-3, 4, (count,), generator=generator)
    return torch.nextafter(values, torch.where(steps > 0, 2.0, -1.0).float()).where(steps != 0, values)


@pytest.mark.parametrize("bits", [1, 8, 10, 12, 16, 20, 24])
def test_codes_are_the_exact_codes_of_float32_inputs(bits):
    """Codes are computed in float64 inside the kernels (quantize_ste and the fused sensor kernel): no flips against
    a float64 quantization, even for inputs an ulp from a threshold (float32 arithmetic flips many of those)."""
    raw = _near_thresholds(bits).reshape(4, 1, 50, 100)
    levels = (1 << bits) - 1
    reference = torch.floor(raw.double().clamp(0, 1) * levels + 0.5)  # codes of the float32 values, in float64
    assert torch.equal(torch.round(quantize_ste(raw, bits).double() * levels), reference)
    rgb = raw.expand(4, 3, 50, 100).contiguous()
    phi = torch.tensor([1.0, 0.0, 0.0]).repeat(2, 2, 1)  # the red channel alone: raw itself reaches the ADC
    assert torch.equal(torch.round(sensor_capture(rgb, phi, bits=bits).double() * levels), reference)
    if bits >= 16:  # the float32 formula does flip codes here, so the test can tell the two apart
        assert not torch.equal(torch.round(quantize_reference(raw, bits).double() * levels), reference)


def test_max_mode_ignores_infinite_pixels():
    raw = torch.tensor([[0.1, 0.2, 0.4, float("inf")]])
    out = quantize_ste(raw, 8, mode="max")
    assert out[0, 2].item() == pytest.approx(0.4) and out[0, 0].item() == pytest.approx(0.1, abs=0.4 / 255)


def _double_backward(function, *inputs):
    first = function(*inputs)
    grads = torch.autograd.grad(first.sum(), [x for x in inputs if x.requires_grad], create_graph=True)
    sum(g.sum() for g in grads).backward()


@pytest.mark.parametrize("name", ["cfa", "noise", "quantize", "psf"])
def test_double_backward_is_a_clear_error(name):
    rgb = torch.rand(1, 3, 5, 5, dtype=torch.float64, requires_grad=True)
    cases = {
        "cfa": (cfa_mosaic, rgb, torch.rand(2, 2, 3, dtype=torch.float64, requires_grad=True)),
        "noise": (lambda r: poisson_gaussian(r, 0.01, 0.01, 3), rgb),
        "quantize": (lambda r: quantize_ste(r, 8), rgb),
        "psf": (psf_conv, rgb, torch.rand(3, 2, 2, 3, 3, dtype=torch.float64, requires_grad=True)),
    }
    function, *inputs = cases[name]
    with pytest.raises(RuntimeError, match="no autograd formula"):
        _double_backward(function, *inputs)


@pytest.mark.parametrize("shot,read,error", [(-0.1, 0.0, ValueError), (float("nan"), 0.0, ValueError),
                                             (0.1, float("inf"), ValueError), (True, 0.0, TypeError)])
def test_noise_levels_policy(shot, read, error):
    with pytest.raises(error):
        poisson_gaussian(torch.rand(2, 3), shot, read, 1)


def test_zero_dimensional_raw_accepted():
    assert quantize_ste(torch.tensor(0.5), 8).shape == ()
    assert poisson_gaussian(torch.tensor(0.5), 0.01, 0.01, 1).shape == ()


def test_numpy_inputs_rejected_with_type_error():
    with pytest.raises(TypeError):
        quantize_ste(torch.rand(2, 3).numpy(), 8)
    with pytest.raises(TypeError):
        poisson_gaussian(torch.rand(2, 3).numpy(), 0.1, 0.1, 1)
