import pytest
import torch

from tests.conftest import device_params
from warpsense.ops import cfa_mosaic, poisson_gaussian, quantize_ste
from warpsense.ops.sensor import sensor_capture


def chain(rgb, phi, shot, read, seed, bits):
    raw = cfa_mosaic(rgb, phi)
    if shot is not None:
        raw = poisson_gaussian(raw, shot, read, seed)
    return quantize_ste(raw, bits) if bits else raw


def test_smoke_and_cardinality():
    out = sensor_capture(torch.rand(2, 3, 5, 7), torch.rand(2, 2, 3), 0.01, 0.002, 3, 10)
    assert out.shape == (2, 1, 5, 7)


def test_exception():
    with pytest.raises(ValueError, match="rgb"):
        sensor_capture(torch.rand(2, 1, 5, 7), torch.rand(2, 2, 3))
    with pytest.raises(ValueError, match="both"):
        sensor_capture(torch.rand(1, 3, 4, 4), torch.rand(2, 2, 3), shot=0.1)
    with pytest.raises(ValueError, match="bits"):
        sensor_capture(torch.rand(1, 3, 4, 4), torch.rand(2, 2, 3), bits=0)


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("stages", ["all", "no_noise", "no_quantize", "mosaic_only"])
def test_feature_equals_chain_of_stage_ops(device, dtype, stages):
    torch.manual_seed(1)
    rgb = (torch.rand(2, 3, 9, 10, dtype=dtype, device=device) * 1.2 - 0.05).requires_grad_()
    phi = torch.rand(2, 2, 3, dtype=dtype, device=device).requires_grad_()
    shot = torch.tensor(0.02, dtype=dtype, device=device, requires_grad=True)
    read = torch.tensor(0.01, dtype=dtype, device=device, requires_grad=True)
    noisy = stages in ("all", "no_quantize")
    bits = 8 if stages in ("all", "no_noise") else None
    arguments = (shot if noisy else None, read if noisy else None, 77, bits)
    fused, reference = sensor_capture(rgb, phi, *arguments), chain(rgb, phi, *arguments)
    torch.testing.assert_close(fused, reference)
    grad = torch.randn_like(fused)
    wanted = [rgb, phi, shot, read] if noisy else [rgb, phi]
    for mine, theirs in zip(torch.autograd.grad(fused, wanted, grad), torch.autograd.grad(reference, wanted, grad)):
        torch.testing.assert_close(mine, theirs)


def test_per_image_seeds_match_the_noise_op():
    rgb, phi = torch.rand(3, 3, 6, 6, dtype=torch.float64), torch.rand(1, 1, 3, dtype=torch.float64)
    seeds = torch.tensor([5, 9, 5])
    out = sensor_capture(rgb, phi, 0.05, 0.01, seeds)
    torch.testing.assert_close(out, poisson_gaussian(cfa_mosaic(rgb, phi), 0.05, 0.01, seeds))
    # an image's noise depends on its own seed, not on its place in the batch
    alone = sensor_capture(rgb[2:], phi, 0.05, 0.01, seeds[2:])
    torch.testing.assert_close(out[2:], alone)


def test_gradcheck():
    rgb = torch.rand(1, 3, 5, 6, dtype=torch.float64, requires_grad=True)
    phi = torch.rand(2, 2, 3, dtype=torch.float64, requires_grad=True)
    shot = torch.tensor(0.03, dtype=torch.float64, requires_grad=True)
    read = torch.tensor(0.02, dtype=torch.float64, requires_grad=True)
    # no quantization: the straight-through estimator is not the derivative of a step function
    assert torch.autograd.gradcheck(lambda *x: sensor_capture(*x, seed=11), (rgb, phi, shot, read))


def test_double_backward_raises():
    rgb = torch.rand(1, 3, 4, 4, dtype=torch.float64, requires_grad=True)
    out = sensor_capture(rgb, torch.rand(2, 2, 3, dtype=torch.float64), 0.01, 0.01, 1, 10)
    (grad,) = torch.autograd.grad(out.sum(), rgb, create_graph=True)
    with pytest.raises(RuntimeError, match="no autograd formula"):
        grad.sum().backward()
