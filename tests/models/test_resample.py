"""Deterministic-backward resizing and pooling (warpsense.models.resample) against torch's own ops: values,
gradients and float64 gradchecks."""

import pytest
import torch
import torch.nn.functional as F

from warpsense.models.resample import adaptive_avg_pool, resize_bilinear, upsample2x

SHAPES = [(2, 3, 5, 7), (1, 2, 1, 1), (1, 1, 1, 4), (2, 4, 22, 30)]


@pytest.mark.parametrize("shape", SHAPES)
def test_upsample2x_is_torch_bilinear(shape):
    x = torch.rand(*shape, dtype=torch.float64)
    size = (2 * shape[-2], 2 * shape[-1])
    expected = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    torch.testing.assert_close(upsample2x(x), expected, rtol=0, atol=1e-14)
    assert resize_bilinear(x, size).shape == expected.shape


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("size", [(11, 21), (22, 30), (3, 5), (1, 1)])
def test_resize_is_torch_bilinear_values_and_gradients(shape, size):
    """Any target size (up, down, mixed), with the gradient of a random upstream signal."""
    x = torch.rand(*shape, dtype=torch.float64, requires_grad=True)
    upstream = torch.randn(*shape[:2], *size, dtype=torch.float64)
    ours = resize_bilinear(x, size)
    (grad_ours,) = torch.autograd.grad((ours * upstream).sum(), x)
    expected = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    (grad_expected,) = torch.autograd.grad((expected * upstream).sum(), x)
    torch.testing.assert_close(ours, expected, rtol=0, atol=1e-13)
    torch.testing.assert_close(grad_ours, grad_expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("bins", [1, 2, 4])
def test_adaptive_pool_is_torch_values_and_gradients(shape, bins):
    """Including maps smaller than the bins (torch's windows then repeat pixels)."""
    x = torch.rand(*shape, dtype=torch.float64, requires_grad=True)
    upstream = torch.randn(*shape[:2], bins, bins, dtype=torch.float64)
    ours = adaptive_avg_pool(x, bins)
    (grad_ours,) = torch.autograd.grad((ours * upstream).sum(), x)
    expected = F.adaptive_avg_pool2d(x, bins)
    (grad_expected,) = torch.autograd.grad((expected * upstream).sum(), x)
    torch.testing.assert_close(ours, expected, rtol=0, atol=1e-14)
    torch.testing.assert_close(grad_ours, grad_expected, rtol=0, atol=1e-13)


def test_gradcheck():
    x = torch.rand(1, 2, 3, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(upsample2x, (x,))
    assert torch.autograd.gradcheck(lambda t: resize_bilinear(t, (5, 9)), (x,))
    assert torch.autograd.gradcheck(lambda t: adaptive_avg_pool(t, 2), (x,))


def test_dtype_and_device_follow_the_input():
    x = torch.rand(1, 2, 3, 4, dtype=torch.float32)
    for out in (upsample2x(x), resize_bilinear(x, (5, 9)), adaptive_avg_pool(x, 2)):
        assert out.dtype == torch.float32 and out.device == x.device
