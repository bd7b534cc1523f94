import pytest
import torch
import torch.nn.functional as F

from tests.conftest import assert_matches_reference, device_params
from warpsense.ops import psf_conv
from warpsense.ops.psf import psf_conv_fft
from warpsense.ops.reference import bilinear_node_weights, psf_conv_reference


def random_psf(channels, grid_y, grid_x, size, dtype=torch.float64, device="cpu"):
    psf = torch.rand(channels, grid_y, grid_x, size, size, dtype=dtype, device=device) + 0.05
    return psf / psf.sum(dim=(-2, -1), keepdim=True)


@pytest.mark.parametrize("device", device_params())
def test_smoke(device):
    out = psf_conv(torch.rand(1, 3, 8, 9, device=device), random_psf(3, 2, 2, 3, torch.float32, device))
    assert out.shape == (1, 3, 8, 9) and out.device.type == device


def test_exception():
    with pytest.raises(ValueError, match="K odd"):
        psf_conv(torch.rand(1, 3, 8, 8), torch.rand(3, 1, 1, 4, 4))
    with pytest.raises(ValueError, match="channels"):
        psf_conv(torch.rand(1, 2, 8, 8), torch.rand(3, 1, 1, 3, 3))
    with pytest.raises(ValueError, match="method"):
        psf_conv(torch.rand(1, 3, 8, 8), torch.rand(3, 1, 1, 3, 3), method="magic")


@pytest.mark.parametrize("shape,grid,size", [((2, 1, 5, 7), (1, 1), 3), ((1, 3, 9, 6), (3, 2), 5), ((1, 1, 4, 4), (2, 2), 7)])
def test_cardinality(shape, grid, size):
    assert psf_conv(torch.rand(shape), random_psf(shape[1], *grid, size, torch.float32)).shape == shape


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("grid", [(1, 1), (2, 3), (3, 3)])
def test_feature_vs_reference(device, grid):
    image = torch.rand(2, 3, 11, 13, dtype=torch.float64, device=device)
    psf = random_psf(3, *grid, 5, device=device)
    torch.testing.assert_close(psf_conv(image, psf), psf_conv_reference(image, psf))


def test_invariant_equals_conv2d_with_flipped_kernel_float32():
    image = torch.rand(2, 3, 20, 24)
    psf = random_psf(3, 1, 1, 7, torch.float32)
    padded = F.pad(image, (3, 3, 3, 3), mode="replicate")
    expected = F.conv2d(padded, psf[:, 0, 0].flip(-1, -2).unsqueeze(1), groups=3)
    torch.testing.assert_close(psf_conv(image, psf), expected, rtol=1e-5, atol=1e-6)


def test_point_source_renders_as_psf_not_flipped():
    # asymmetric PSF; the delta sits at a node centre so the interpolated PSF is that node's PSF
    psf = random_psf(1, 3, 3, 5)
    image = torch.zeros(1, 1, 33, 33, dtype=torch.float64)
    y, x = 16, 5  # centre of tile (1, 0) of a 3x3 tiling of 33x33 (tiles of 11 pixels)
    image[0, 0, y, x] = 1.0
    out = psf_conv(image, psf)
    torch.testing.assert_close(out[0, 0, y - 2 : y + 3, x - 2 : x + 3], psf[0, 1, 0])
    assert out.sum().item() == pytest.approx(1.0)


def test_point_source_between_nodes_renders_interpolated_psf():
    psf = random_psf(1, 2, 2, 3)
    image = torch.zeros(1, 1, 20, 20, dtype=torch.float64)
    image[0, 0, 8, 11] = 1.0
    weights = bilinear_node_weights(20, 20, 2, 2, torch.float64, "cpu")[:, :, 8, 11]
    expected = (weights[..., None, None] * psf[0]).sum(dim=(0, 1))
    torch.testing.assert_close(psf_conv(image, psf)[0, 0, 7:10, 10:13], expected)


def test_energy_conservation_away_from_borders():
    psf = random_psf(3, 3, 3, 5)
    image = torch.zeros(1, 3, 24, 24, dtype=torch.float64)
    image[..., 4:20, 4:20] = torch.rand(1, 3, 16, 16, dtype=torch.float64)
    torch.testing.assert_close(psf_conv(image, psf).sum(dim=(-2, -1)), image.sum(dim=(-2, -1)))


def test_gradcheck_image_and_psf():
    image = torch.rand(2, 2, 7, 8, dtype=torch.float64, requires_grad=True)
    psf = random_psf(2, 2, 3, 3).requires_grad_()
    assert torch.autograd.gradcheck(psf_conv, (image, psf))
    # kernel larger than the image: every border case of the clamped adjoint at once
    small = torch.rand(1, 1, 3, 2, dtype=torch.float64, requires_grad=True)
    big = random_psf(1, 2, 1, 5).requires_grad_()
    assert torch.autograd.gradcheck(psf_conv, (small, big))


@pytest.mark.parametrize("device", device_params())
def test_gradients_match_reference(device):
    image = torch.rand(2, 3, 12, 10, dtype=torch.float64, device=device, requires_grad=True)
    psf = random_psf(3, 3, 2, 5, device=device).requires_grad_()
    grad = torch.rand(2, 3, 10, 12, dtype=torch.float64, device=device).transpose(-1, -2)
    assert_matches_reference(psf_conv, psf_conv_reference, (image, psf), grad)


def test_fft_method_exact_for_invariant_psf():
    image = torch.rand(1, 3, 16, 18, dtype=torch.float64)
    psf = random_psf(3, 1, 1, 5)
    torch.testing.assert_close(psf_conv(image, psf, method="fft"), psf_conv(image, psf), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(psf_conv_fft(image, psf[:, 0, 0]), psf_conv_reference(image, psf), rtol=1e-10, atol=1e-12)


def test_alternative_methods_error_versus_direct():
    """Stated error of the approximations on white noise (the worst case) through the 80 deg lens' 5x5 grid: the
    patch-wise method (seams, no blending) is off by ~19% of the image max at worst, FFT with the mean PSF by ~30%;
    neither is exact, and patch-wise is the closer of the two."""
    from warpsense.optics import Lens

    psf = Lens.from_json("phone_80deg").psf_grid()[:, :, :, 4:11, 4:11]
    psf = psf / psf.sum(dim=(-2, -1), keepdim=True)
    image = torch.rand(1, 3, 40, 50, dtype=torch.float64)
    exact = psf_conv(image, psf)
    errors = {m: (psf_conv(image, psf, method=m) - exact).abs().max().item() / exact.max().item() for m in ("patch", "fft")}
    assert 1e-3 < errors["patch"] < 0.25 and 1e-3 < errors["fft"] < 0.4
    assert errors["patch"] < errors["fft"]


def test_inputs_not_mutated_and_autocast():
    image, psf = torch.rand(1, 3, 6, 6), random_psf(3, 1, 1, 3, torch.float32)
    copies = image.clone(), psf.clone()
    psf_conv(image, psf)
    assert torch.equal(image, copies[0]) and torch.equal(psf, copies[1])
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert psf_conv(image.bfloat16(), psf).dtype == torch.float32


@pytest.mark.cuda
@pytest.mark.parametrize("grid,size", [((1, 1), 15), ((5, 5), 15), ((3, 2), 7)])
def test_cuda_matches_reference_forward_and_backward(grid, size):
    image = torch.rand(2, 3, 40, 52, dtype=torch.float64, device="cuda", requires_grad=True)
    psf = random_psf(3, *grid, size, device="cuda").requires_grad_()
    grad = torch.rand(2, 3, 40, 52, dtype=torch.float64, device="cuda")
    assert_matches_reference(psf_conv, psf_conv_reference, (image, psf), grad)
