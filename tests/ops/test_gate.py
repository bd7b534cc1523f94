import pytest
import torch

from tests.conftest import assert_matches_reference, device_params
from warpsense.ops import channel_gate
from warpsense.ops.reference import channel_gate_reference as reference


def channels_last(*shape, dtype=torch.float64, device="cpu"):
    return torch.randn(*shape, dtype=dtype, device=device).contiguous(memory_format=torch.channels_last)


def gates(batch, channels, dtype=torch.float64, device="cpu"):
    return torch.rand(batch, channels, 1, 1, dtype=dtype, device=device)


@pytest.mark.parametrize("device", device_params())
def test_smoke(device):
    out = channel_gate(channels_last(2, 4, 3, 5, device=device), gates(2, 4, device=device))
    assert out.shape == (2, 4, 3, 5) and out.device.type == device
    assert out.is_contiguous(memory_format=torch.channels_last)


def test_exception():
    with pytest.raises(ValueError, match="even number of channels"):
        channel_gate(channels_last(2, 3, 4, 4), gates(2, 3))
    with pytest.raises(ValueError, match=r"gate must be \[B, C, 1, 1\] or \[B, C\] = \[2, 4\]"):
        channel_gate(channels_last(2, 4, 4, 4), gates(1, 4))
    with pytest.raises(ValueError, match="residual must have x's shape"):
        channel_gate(channels_last(2, 4, 4, 4), gates(2, 4), channels_last(2, 4, 4, 5))
    with pytest.raises(TypeError, match="gate must be floating point"):
        channel_gate(channels_last(2, 4, 4, 4), torch.ones(2, 4, 1, 1, dtype=torch.int64))


@pytest.mark.parametrize("shape", [(1, 2, 1, 1), (2, 6, 3, 1), (3, 10, 7, 9)])
def test_cardinality(shape):
    assert channel_gate(channels_last(*shape), gates(*shape[:2])).shape == shape
    assert channel_gate(channels_last(*shape), gates(*shape[:2]).flatten(1)).shape == shape  # [B, C] gates


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("layout", ["channels_last", "contiguous"])
@pytest.mark.parametrize("with_residual", [False, True])
def test_feature_vs_reference(device, layout, with_residual):
    """Equal to torch's broadcast multiply (and add) in float64, forward and the gradients of x, the gates and the
    residual, from either memory layout; more pixels than the launch has pixel groups."""
    x = channels_last(3, 6, 11, 13, device=device)
    residual = channels_last(3, 6, 11, 13, device=device) if with_residual else None
    if layout == "contiguous":
        x = x.contiguous()
        residual = None if residual is None else residual.contiguous()
    inputs = [x.requires_grad_(), gates(3, 6, device=device).requires_grad_()]
    if residual is not None:
        inputs.append(residual.requires_grad_())
    assert_matches_reference(channel_gate, reference, inputs, torch.randn(3, 6, 11, 13, dtype=torch.float64,
                                                                           device=device))


def test_gradcheck():
    x = channels_last(2, 4, 3, 3).requires_grad_()
    gate = gates(2, 4).requires_grad_()
    residual = channels_last(2, 4, 3, 3).requires_grad_()
    assert torch.autograd.gradcheck(channel_gate, (x, gate, residual))
    assert torch.autograd.gradcheck(channel_gate, (x, gate))


@pytest.mark.parametrize("device", device_params())
def test_bfloat16_computes_in_float32(device):
    """bfloat16 in and out, the product and the sum in float32 and rounded once: within one bfloat16 rounding of
    the float64 result on the same inputs; the gates' gradient (summed over the pixels in float32) within a
    bfloat16 rounding of each term."""
    x = channels_last(2, 8, 9, 10, dtype=torch.bfloat16, device=device).requires_grad_()
    gate = gates(2, 8, torch.bfloat16, device).requires_grad_()
    residual = channels_last(2, 8, 9, 10, dtype=torch.bfloat16, device=device)
    out = channel_gate(x, gate, residual)
    assert out.dtype == torch.bfloat16
    expected = reference(x.double(), gate.double(), residual.double())
    torch.testing.assert_close(out.double(), expected, rtol=2**-8, atol=1e-6)
    grad = torch.randn(2, 8, 9, 10, device=device).bfloat16()
    grad_x, grad_gate = torch.autograd.grad(out, (x, gate), grad)
    assert grad_x.dtype == grad_gate.dtype == torch.bfloat16
    torch.testing.assert_close(grad_x.double(), grad.double() * gate.double(), rtol=2**-8, atol=1e-6)
    exact = (grad.double() * x.double()).sum(dim=(2, 3), keepdim=True)
    torch.testing.assert_close(grad_gate.double(), exact, rtol=2**-7, atol=90 * 2**-8)


@pytest.mark.parametrize("device", device_params())
def test_backward_is_deterministic(device):
    x = channels_last(4, 8, 16, 16, dtype=torch.float32, device=device).requires_grad_()
    gate = gates(4, 8, torch.float32, device).requires_grad_()
    grad = torch.randn(4, 8, 16, 16, device=device)
    first, second = (torch.autograd.grad(channel_gate(x, gate), (x, gate), grad) for _ in range(2))
    assert all(torch.equal(a, b) for a, b in zip(first, second))
