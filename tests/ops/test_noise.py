import math

import pytest
import torch

from tests.conftest import assert_matches_reference, device_params
from warpsense.ops import poisson_gaussian, poisson_gaussian_exact
from warpsense.ops.reference import poisson_gaussian_reference, standard_normal_reference


def standard_normal(shape, seed, device="cpu", dtype=torch.float64):
    """The kernel's eps: with shot = 0 and read = 1 the op returns eps itself."""
    return poisson_gaussian(torch.zeros(shape, dtype=dtype, device=device), 0.0, 1.0, seed)


@pytest.mark.parametrize("device", device_params())
def test_smoke(device):
    out = poisson_gaussian(torch.rand(2, 1, 4, 5, device=device), 0.015, 0.002, seed=1)
    assert out.shape == (2, 1, 4, 5) and torch.isfinite(out).all()


def test_exception():
    with pytest.raises(ValueError, match="non-empty"):
        poisson_gaussian(torch.zeros(0), 0.1, 0.1, 0)
    with pytest.raises(ValueError, match="0-d tensor"):
        poisson_gaussian(torch.rand(3), torch.rand(2), 0.1, 0)


@pytest.mark.parametrize("shape", [(7,), (2, 3), (2, 1, 5, 6), (1, 1, 1, 1)])
def test_cardinality(shape):
    assert poisson_gaussian(torch.rand(shape), 0.01, 0.01, 3).shape == shape


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_feature_vs_reference(dtype):
    raw = torch.rand(2, 1, 6, 7, dtype=dtype) * 1.2 - 0.1
    eps = standard_normal(raw.shape, 11, dtype=dtype)
    expected = poisson_gaussian_reference(raw, 0.015, 0.002, eps)
    torch.testing.assert_close(poisson_gaussian(raw, 0.015, 0.002, 11), expected)


@pytest.mark.parametrize("signal", [0.0, 0.05, 0.3, 0.9])
def test_mean_and_variance_match_model(signal):
    # 200k draws: the standard error of the mean is sigma / 447 and of the variance about var * 0.32 %
    shot, read, count = 0.015, 0.002, 200_000
    out = poisson_gaussian(torch.full((count,), signal, dtype=torch.float64), shot, read, seed=5)
    variance = shot * signal + read**2
    assert abs(out.mean().item() - signal) < 5 * math.sqrt(variance / count)
    assert abs(out.var().item() / variance - 1) < 0.02


def test_same_seed_same_noise_new_seed_different():
    raw = torch.rand(1000)
    a, b, c = (poisson_gaussian(raw, 0.01, 0.01, s) for s in (3, 3, 4))
    assert torch.equal(a, b)
    assert not torch.allclose(a, c)
    # counter-based: element i depends only on (seed, i), not on the tensor's size or shape
    assert torch.equal(poisson_gaussian(raw[:10], 0.01, 0.01, 3), a[:10])


def test_gradcheck():
    raw = (torch.rand(3, 4, dtype=torch.float64) + 0.05).requires_grad_()
    shot = torch.tensor(0.02, dtype=torch.float64, requires_grad=True)
    read = torch.tensor(0.05, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda r, s, q: poisson_gaussian(r, s, q, 9), (raw, shot, read))


def test_gradients_match_reference():
    raw = (torch.rand(2, 5, dtype=torch.float64) * 1.2 - 0.1).requires_grad_()
    shot = torch.tensor(0.02, dtype=torch.float64, requires_grad=True)
    read = torch.tensor(0.01, dtype=torch.float64, requires_grad=True)
    eps = standard_normal(raw.shape, 2)
    grad = torch.rand(5, 2, dtype=torch.float64).T
    assert_matches_reference(lambda r, s, q: poisson_gaussian(r, s, q, 2),
                             lambda r, s, q: poisson_gaussian_reference(r, s, q, eps), (raw, shot, read), grad)


def test_zero_noise_is_identity_with_unit_gradient():
    raw = torch.rand(10, dtype=torch.float64, requires_grad=True)
    out = poisson_gaussian(raw, 0.0, 0.0, 1)
    assert torch.equal(out, raw.detach())
    (grad,) = torch.autograd.grad(out.sum(), raw)
    assert torch.equal(grad, torch.ones_like(raw))


def test_exact_poisson_statistics():
    shot, signal = 0.01, 0.2  # mean photon count 20
    out = poisson_gaussian_exact(torch.full((100_000,), signal), shot, 0.0, seed=3)
    photons = out / shot
    assert torch.allclose(photons, photons.round(), atol=1e-3)  # integer counts
    assert abs(photons.mean().item() - 20) < 0.1 and abs(photons.var().item() / 20 - 1) < 0.03


def test_inputs_not_mutated_and_autocast():
    raw = torch.rand(2, 8)
    copy = raw.clone()
    poisson_gaussian(raw, 0.1, 0.1, 0)
    assert torch.equal(raw, copy)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert poisson_gaussian(raw.bfloat16(), 0.1, 0.1, 0).dtype == torch.float32


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("seed", [0, 77, -5, 2**40 + 3])
def test_counter_based_numbers_match_numpy_generator(device, seed):
    """eps on every device equals an independent NumPy implementation of the PCG-hash + Box-Muller generator
    (float32 transcendental functions differ by a few ulp between libm, CUDA and NumPy)."""
    from warpsense.ops._warp import seed_int32

    eps = standard_normal((50_000,), seed, device, torch.float32).cpu().numpy()
    expected = standard_normal_reference(seed_int32(seed), 50_000)
    assert abs(eps - expected).max() < 2e-6


@pytest.mark.cuda
def test_cuda_gradients_match_reference():
    raw = (torch.rand(4, 1, 16, 16, dtype=torch.float64, device="cuda") * 1.2 - 0.1).requires_grad_()
    shot = torch.tensor(0.02, dtype=torch.float64, device="cuda", requires_grad=True)
    read = torch.tensor(0.01, dtype=torch.float64, device="cuda", requires_grad=True)
    eps = standard_normal(raw.shape, 5, "cuda")
    assert_matches_reference(lambda r, s, q: poisson_gaussian(r, s, q, 5),
                             lambda r, s, q: poisson_gaussian_reference(r, s, q, eps), (raw, shot, read),
                             torch.rand_like(raw))
