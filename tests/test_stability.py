"""Stiff and extreme cases: outputs and gradients finite wherever defined; NaN propagates locally (documented),
never turns into a plausible value."""


import pytest
import torch

from tests.conftest import device_params
from warpsense.camera import Exposure
from warpsense.ops import cfa_mosaic, poisson_gaussian, psf_conv, quantize_ste

pytestmark = pytest.mark.parametrize("device", device_params())


def _psf(size, grid=(1, 1), device="cpu"):
    psf = torch.rand(3, *grid, size, size, device=device) + 0.1
    return psf / psf.sum(dim=(-2, -1), keepdim=True)


def test_zero_negative_saturated_inputs_finite(device):
    for fill in (0.0, -1.0, 1.0, 1e6):
        image = torch.full((1, 3, 5, 6), fill, device=device, requires_grad=True)
        raw = cfa_mosaic(image, torch.rand(2, 2, 3, device=device))
        blurred = psf_conv(image, _psf(3, device=device))
        noisy = poisson_gaussian(raw, 0.015, 0.002, 1)
        quantized = quantize_ste(noisy, 10)
        for out in (raw, blurred, noisy, quantized):
            assert torch.isfinite(out).all(), fill
        (grad,) = torch.autograd.grad(quantized.sum() + blurred.sum(), image)
        assert torch.isfinite(grad).all()
        assert quantized.min() >= 0 and quantized.max() <= 1


def test_nan_and_inf_propagate_locally(device):
    image = torch.rand(1, 3, 6, 6, device=device)
    image[0, :, 2, 3] = float("nan")
    raw = cfa_mosaic(image, torch.rand(2, 2, 3, device=device))
    assert torch.isnan(raw[0, 0, 2, 3]) and torch.isnan(raw).sum() == 1
    assert torch.isnan(poisson_gaussian(raw, 0.01, 0.01, 0)).sum() == 1
    quantized = quantize_ste(raw, 8)
    assert torch.isnan(quantized).sum() == 1 and torch.isnan(quantized[0, 0, 2, 3])
    blurred = psf_conv(image, _psf(3, device=device))
    assert torch.isnan(blurred).sum() == 3 * 9  # exactly the 3x3 support around the NaN source, per channel
    infinite = torch.tensor([[float("inf"), -float("inf"), 0.5]], device=device)
    assert quantize_ste(infinite, 4).tolist() == [[1.0, 0.0, pytest.approx(8 / 15)]]  # 7.5 rounds half up to code 8


def test_max_mode_black_and_negative_frames(device):
    for frame in (torch.zeros(2, 1, 4, 4, device=device), -torch.rand(2, 1, 4, 4, device=device)):
        frame.requires_grad_()
        out = quantize_ste(frame, 10, mode="max")
        assert torch.equal(out, torch.zeros_like(out))
        (grad,) = torch.autograd.grad(out.sum(), frame)
        assert torch.isfinite(grad).all()


@pytest.mark.parametrize("bits", range(1, 17))
def test_every_bit_depth(device, bits):
    raw = torch.rand(1, 1, 8, 8, device=device, dtype=torch.float64)
    out = quantize_ste(raw, bits)
    steps = 2**bits - 1
    assert torch.allclose(out * steps, (out * steps).round(), atol=1e-6)
    assert (out - raw).abs().max() <= 0.5 / steps + 1e-9


def test_exposure_logit_extremes(device):
    for logit, gain in ((-50.0, 0.25), (50.0, 4.0)):
        module = Exposure(logit).to(device)
        out = module(torch.rand(1, 3, 2, 2, device=device))
        out.sum().backward()
        assert module.gain().item() == pytest.approx(gain)
        assert torch.isfinite(module.gain_logit.grad) and torch.isfinite(out).all()


@pytest.mark.parametrize("shot,read", [(0.0, 0.0), (0.0, 0.1), (0.1, 0.0), (1e4, 1e3)])
def test_noise_levels_zero_and_huge(device, shot, read):
    raw = torch.rand(1, 1, 8, 8, device=device, dtype=torch.float64).requires_grad_()
    shot_t = torch.tensor(shot, device=device, dtype=torch.float64, requires_grad=True)
    read_t = torch.tensor(read, device=device, dtype=torch.float64, requires_grad=True)
    out = poisson_gaussian(raw, shot_t, read_t, 3)
    grads = torch.autograd.grad(out.sum(), (raw, shot_t, read_t))
    assert torch.isfinite(out).all() and all(torch.isfinite(g).all() for g in grads)
    if shot == 0 and read == 0:
        assert torch.equal(out, raw.detach())


def test_psf_larger_than_image_and_tiny_sizes(device):
    for shape in ((1, 3, 1, 1), (2, 3, 1, 5), (1, 3, 3, 2), (1, 3, 7, 9)):
        image = torch.rand(shape, device=device, requires_grad=True)
        psf = _psf(9, (2, 2), device=device).requires_grad_()
        out = psf_conv(image, psf)
        assert out.shape == shape and torch.isfinite(out).all()
        grads = torch.autograd.grad(out.sum(), (image, psf))
        assert all(torch.isfinite(g).all() for g in grads)
    # a 1x1 image is constant under clamp-to-edge: every normalised PSF returns it unchanged
    single = torch.rand(1, 3, 1, 1, device=device)
    torch.testing.assert_close(psf_conv(single, _psf(9, device=device)), single)
    assert cfa_mosaic(torch.rand(1, 3, 1, 1, device=device), torch.rand(3, 3, 3, device=device)).shape == (1, 1, 1, 1)


def test_non_contiguous_and_channels_last(device):
    image = torch.rand(2, 3, 10, 12, device=device)
    phi = torch.rand(2, 2, 3, device=device)
    expected_raw = cfa_mosaic(image, phi)
    torch.testing.assert_close(cfa_mosaic(image.to(memory_format=torch.channels_last), phi), expected_raw)
    torch.testing.assert_close(cfa_mosaic(image.transpose(-1, -2).contiguous().transpose(-1, -2), phi), expected_raw)
    psf = _psf(5, (2, 2), device=device)
    torch.testing.assert_close(psf_conv(image.to(memory_format=torch.channels_last), psf), psf_conv(image, psf))
    raw = torch.rand(4, 6, device=device)
    torch.testing.assert_close(quantize_ste(raw.T, 8), quantize_ste(raw.T.contiguous(), 8))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_inputs_compute_in_float32(device, dtype):
    if device == "cpu" and dtype == torch.float16:
        autocast_dtype = torch.bfloat16
    else:
        autocast_dtype = dtype
    image = torch.rand(1, 3, 6, 6, device=device).to(dtype).requires_grad_()
    with torch.autocast(device, dtype=autocast_dtype):
        raw = cfa_mosaic(image, torch.rand(2, 2, 3, device=device))
        blurred = psf_conv(raw.expand(-1, 3, -1, -1), _psf(3, device=device)).mean(1, keepdim=True)
        out = quantize_ste(poisson_gaussian(blurred, 0.01, 0.01, 0), 8)
    assert out.dtype == torch.float32 and torch.isfinite(out).all()
    (grad,) = torch.autograd.grad(out.sum(), image)
    assert grad.dtype == dtype and torch.isfinite(grad.float()).all()
