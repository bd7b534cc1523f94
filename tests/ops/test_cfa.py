import pytest
import torch

from tests.conftest import assert_matches_reference, device_params
from warpsense.camera.cfa import CFA_LAYOUTS, layout_letters, letters_to_phi
from warpsense.ops import cfa_mosaic
from warpsense.ops.reference import cfa_mosaic_reference


@pytest.mark.parametrize("device", device_params())
def test_smoke(device):
    raw = cfa_mosaic(torch.rand(2, 3, 6, 8, device=device), torch.rand(2, 2, 3, device=device))
    assert raw.shape == (2, 1, 6, 8) and raw.device.type == device


def test_exception():
    with pytest.raises(ValueError, match="rgb must be"):
        cfa_mosaic(torch.rand(2, 4, 6, 8), torch.rand(2, 2, 3))
    with pytest.raises(ValueError, match="phi must be"):
        cfa_mosaic(torch.rand(2, 3, 6, 8), torch.rand(2, 3, 3))
    with pytest.raises(TypeError, match="floating"):
        cfa_mosaic(torch.zeros(1, 3, 2, 2, dtype=torch.int64), torch.rand(2, 2, 3))


@pytest.mark.parametrize("tile,height,width", [(1, 3, 5), (2, 5, 7), (3, 7, 4), (4, 8, 9)])
def test_cardinality(tile, height, width):
    raw = cfa_mosaic(torch.rand(3, 3, height, width), torch.rand(tile, tile, 3))
    assert raw.shape == (3, 1, height, width)


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_feature_vs_reference(device, dtype):
    rgb = torch.rand(2, 3, 9, 11, dtype=dtype, device=device)
    phi = torch.rand(3, 3, 3, dtype=dtype, device=device)
    torch.testing.assert_close(cfa_mosaic(rgb, phi), cfa_mosaic_reference(rgb, phi))


@pytest.mark.parametrize("pattern", list(CFA_LAYOUTS))
def test_layout_puts_right_channel_on_right_site(pattern):
    # distinct constant colour planes: the mosaic value tells which filter sits on each site
    rgb = torch.stack([torch.full((4, 6), 1.0), torch.full((4, 6), 10.0), torch.full((4, 6), 100.0)])[None]
    raw = cfa_mosaic(rgb, letters_to_phi(layout_letters(pattern, 2)))[0, 0]
    value = {"R": 1.0, "G": 10.0, "B": 100.0, "C": 111.0, "Y": 11.0}
    for y in range(4):
        for x in range(6):
            assert raw[y, x] == value[CFA_LAYOUTS[pattern][y % 2][x % 2]], (pattern, y, x)


def test_gradcheck():
    rgb = torch.rand(2, 3, 5, 6, dtype=torch.float64, requires_grad=True)
    phi = torch.rand(2, 2, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(cfa_mosaic, (rgb, phi))
    phi3 = torch.rand(3, 3, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(cfa_mosaic, (rgb, phi3))


@pytest.mark.parametrize("device", device_params())
def test_gradients_match_reference_noncontiguous_grad(device):
    rgb = torch.rand(2, 3, 7, 9, dtype=torch.float64, device=device, requires_grad=True)
    phi = torch.rand(2, 2, 3, dtype=torch.float64, device=device, requires_grad=True)
    grad = torch.rand(2, 1, 9, 7, dtype=torch.float64, device=device).transpose(-1, -2)  # non-contiguous
    assert_matches_reference(cfa_mosaic, cfa_mosaic_reference, (rgb, phi), grad)


def test_inputs_not_mutated_and_autocast_runs_in_float32():
    rgb = torch.rand(1, 3, 4, 4)
    phi = torch.rand(2, 2, 3)
    rgb_copy, phi_copy = rgb.clone(), phi.clone()
    cfa_mosaic(rgb, phi).sum()
    assert torch.equal(rgb, rgb_copy) and torch.equal(phi, phi_copy)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        raw = cfa_mosaic(rgb.bfloat16(), phi)
    assert raw.dtype == torch.float32
    torch.testing.assert_close(raw, cfa_mosaic_reference(rgb.bfloat16().float(), phi))


@pytest.mark.cuda
def test_cuda_matches_reference_forward_and_backward():
    rgb = torch.rand(2, 3, 16, 20, dtype=torch.float64, device="cuda", requires_grad=True)
    phi = torch.rand(3, 3, 3, dtype=torch.float64, device="cuda", requires_grad=True)
    grad = torch.rand(2, 1, 16, 20, dtype=torch.float64, device="cuda")
    assert_matches_reference(cfa_mosaic, cfa_mosaic_reference, (rgb, phi), grad)
