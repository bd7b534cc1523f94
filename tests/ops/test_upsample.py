import pytest
import torch

from tests.conftest import assert_matches_reference, device_params
from warpsense.ops import upsample_concat
from warpsense.ops.reference import upsample_concat_reference as reference


def channels_last(*shape, dtype=torch.float64, device="cpu"):
    return torch.rand(*shape, dtype=dtype, device=device).contiguous(memory_format=torch.channels_last)


@pytest.mark.parametrize("device", device_params())
def test_smoke(device):
    out = upsample_concat(torch.rand(2, 3, 4, 5, device=device), torch.rand(2, 2, 8, 10, device=device))
    assert out.shape == (2, 5, 8, 10) and out.device.type == device
    assert out.is_contiguous(memory_format=torch.channels_last)


def test_exception():
    with pytest.raises(ValueError, match=r"skip must be \[B, C2, 2h, 2w\]"):
        upsample_concat(torch.rand(1, 3, 4, 5), torch.rand(1, 2, 8, 9))
    with pytest.raises(ValueError, match="skip must be"):
        upsample_concat(torch.rand(1, 3, 4, 5), torch.rand(2, 2, 8, 10))
    with pytest.raises(ValueError, match="x"):
        upsample_concat(torch.rand(3, 4, 5), torch.rand(1, 2, 8, 10))
    with pytest.raises(TypeError, match="x must be floating point"):
        upsample_concat(torch.ones(1, 3, 4, 5, dtype=torch.int64), torch.rand(1, 2, 8, 10))
    from warpsense.ops.upsample import _threads

    with pytest.raises(ValueError, match="32-bit indexing"):  # a launch too large for the kernels' int32 thread ids
        _threads(2**31)
    assert _threads(2**31 - 1) == 2**31 - 1


@pytest.mark.parametrize("shape,skip_channels", [((1, 1, 1, 1), 1), ((2, 3, 1, 4), 2), ((1, 4, 5, 3), 7)])
def test_cardinality(shape, skip_channels):
    batch, channels, height, width = shape
    out = upsample_concat(torch.rand(shape), torch.rand(batch, skip_channels, 2 * height, 2 * width))
    assert out.shape == (batch, channels + skip_channels, 2 * height, 2 * width)


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("layout", ["channels_last", "contiguous"])
def test_feature_vs_reference(device, layout):
    """Equal to torch's resize and concatenation, edges included (a 1-pixel-high input: both edge rules at once),
    from either memory layout."""
    for shape in ((2, 3, 6, 7), (1, 2, 1, 5)):
        x = torch.rand(*shape, dtype=torch.float64, device=device)
        skip = torch.rand(shape[0], 4, 2 * shape[2], 2 * shape[3], dtype=torch.float64, device=device)
        if layout == "channels_last":
            x, skip = (t.contiguous(memory_format=torch.channels_last) for t in (x, skip))
        torch.testing.assert_close(upsample_concat(x, skip), reference(x, skip), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("device", device_params())
def test_gradients_match_reference(device):
    x = channels_last(2, 3, 5, 4, device=device).requires_grad_()
    skip = channels_last(2, 2, 10, 8, device=device).requires_grad_()
    grad = torch.rand(2, 5, 10, 8, dtype=torch.float64, device=device)
    assert_matches_reference(upsample_concat, reference, (x, skip), grad)


def test_gradcheck():
    x = channels_last(2, 2, 3, 4).requires_grad_()
    skip = channels_last(2, 1, 6, 8).requires_grad_()
    assert torch.autograd.gradcheck(upsample_concat, (x, skip))
    one = torch.rand(1, 2, 1, 1, dtype=torch.float64, requires_grad=True)  # every output from one input
    assert torch.autograd.gradcheck(upsample_concat, (one, torch.rand(1, 1, 2, 2, dtype=torch.float64)))


@pytest.mark.parametrize("device", device_params())
def test_bfloat16_computes_in_float32(device):
    """bfloat16 in, bfloat16 out, arithmetic in float32: within one bfloat16 rounding of the float64 result."""
    x = channels_last(2, 8, 6, 10, device=device)
    skip = channels_last(2, 3, 12, 20, device=device)
    out = upsample_concat(x.bfloat16(), skip.bfloat16())
    assert out.dtype == torch.bfloat16
    expected = reference(x.bfloat16().double(), skip.bfloat16().double())
    torch.testing.assert_close(out.double(), expected, rtol=2**-8, atol=0)
    mixed = upsample_concat(x.bfloat16(), skip.float())  # promoted like torch.cat
    assert mixed.dtype == torch.float32


@pytest.mark.parametrize("device", device_params())
def test_backward_is_deterministic(device):
    x = channels_last(2, 4, 8, 8, dtype=torch.float32, device=device).requires_grad_()
    skip = channels_last(2, 4, 16, 16, dtype=torch.float32, device=device)
    grad = torch.randn(2, 8, 16, 16, device=device)
    first, second = (torch.autograd.grad(upsample_concat(x, skip), x, grad)[0] for _ in range(2))
    assert torch.equal(first, second)
