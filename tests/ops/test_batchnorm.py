import pytest
import torch

from tests.conftest import device_params
from warpsense.ops import batch_norm_relu
from warpsense.ops.reference import batch_norm_relu_reference as reference


def activations(*shape, dtype=torch.float64, device="cpu", mean=0.5, std=2.0):
    x = torch.randn(*shape, dtype=torch.float64, device=device) * std + mean
    return x.to(dtype).contiguous(memory_format=torch.channels_last)


def affine(channels, dtype=torch.float64, device="cpu"):
    """weight, bias, running_mean, running_var."""
    return (torch.rand(channels, dtype=dtype, device=device) + 0.5, torch.randn(channels, dtype=dtype, device=device),
            torch.randn(channels, dtype=dtype, device=device), torch.rand(channels, dtype=dtype, device=device) + 0.5)


@pytest.mark.parametrize("device", device_params())
def test_smoke(device):
    x = activations(2, 4, 3, 5, dtype=torch.float32, device=device)
    y = batch_norm_relu(x, *affine(4, torch.float32, device))
    assert y.shape == x.shape and y.dtype == torch.float32 and y.device.type == device
    assert y.is_contiguous(memory_format=torch.channels_last)
    assert (y >= 0).all()


def test_exception():
    params = affine(3)
    with pytest.raises(ValueError, match="even number of channels"):
        batch_norm_relu(activations(2, 3, 4, 4), *params)
    with pytest.raises(ValueError, match="more than one value per channel"):
        batch_norm_relu(activations(1, 4, 1, 1), *affine(4))
    with pytest.raises(ValueError, match=r"weight must have shape \[4\]"):
        batch_norm_relu(activations(2, 4, 3, 3), params[0], *affine(4)[1:])
    with pytest.raises(TypeError, match="running_mean must be a contiguous torch.float32 tensor"):
        batch_norm_relu(activations(2, 4, 3, 3, dtype=torch.bfloat16), *affine(4, torch.float64))
    with pytest.raises(ValueError, match="momentum must be in"):
        batch_norm_relu(activations(2, 4, 3, 3), *affine(4), momentum=1.5)
    with pytest.raises(TypeError, match="^batch_norm_relu: momentum must be a float, got NoneType None \\(torch's "
                                        "cumulative average is not supported\\)$"):
        batch_norm_relu(activations(2, 4, 3, 3), *affine(4), momentum=None)  # was "'<=' not supported"
    with pytest.raises(TypeError, match="x must be floating point"):
        batch_norm_relu(torch.ones(2, 4, 3, 3, dtype=torch.int64), *affine(4))


@pytest.mark.parametrize("shape", [(1, 2, 1, 2), (2, 6, 3, 1), (3, 10, 7, 9)])
def test_cardinality(shape):
    y = batch_norm_relu(activations(*shape), *affine(shape[1]))
    assert y.shape == shape


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("layout", ["channels_last", "contiguous"])
def test_feature_vs_reference(device, layout):
    """Output, running statistics (momentum 0.3) and the gradients of x, weight and bias equal torch's batch norm +
    ReLU in float64, from either memory layout; more rows than the launch has row groups, and rows that do not
    fill the last unrolled step."""
    x = activations(3, 6, 11, 13, device=device)
    if layout == "contiguous":
        x = x.contiguous()
    weight, bias, mean, var = affine(6, device=device)
    weight.requires_grad_()
    bias.requires_grad_()
    x.requires_grad_()
    mine_mean, mine_var = mean.clone(), var.clone()
    y = batch_norm_relu(x, weight, bias, mine_mean, mine_var, momentum=0.3)
    expected = reference(x, weight, bias, mean, var, momentum=0.3)
    torch.testing.assert_close(y, expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(mine_mean, mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(mine_var, var, rtol=1e-12, atol=1e-12)
    assert (expected == 0).any() and (expected > 0).any()  # both sides of the ReLU
    grad = torch.randn_like(expected)
    for mine, theirs in zip(torch.autograd.grad(y, (x, weight, bias), grad),
                            torch.autograd.grad(expected, (x, weight, bias), grad)):
        torch.testing.assert_close(mine, theirs, rtol=1e-10, atol=1e-12)


def test_feature_statistics_of_data_far_from_zero():
    """A mean 1e4 times the spread (float32): the shifted sums keep the variance that E[x^2] - E[x]^2 would lose
    (float32 has 24 bits; x^2 ~ 1e8 carries the variance ~1 in its last bits). The output is within float32's
    spacing at 1e4 (9.8e-4, the mean's own rounding) of the float64 result."""
    x = activations(4, 2, 16, 16, mean=1e4, std=1.0).float()
    weight, bias, mean, var = affine(2)
    y = batch_norm_relu(x, weight.float(), bias.float(), mean.float(), var.float())
    torch.testing.assert_close(y.double(), reference(x.double(), weight, bias, mean, var), rtol=0, atol=2e-3)
    naive = x.square().mean(dim=(0, 2, 3)) - x.mean(dim=(0, 2, 3)).square()  # what unshifted sums would give
    assert (naive - x.double().var(dim=(0, 2, 3), unbiased=False)).abs().max() > 0.1


@pytest.mark.parametrize("device", device_params())
def test_bfloat16_computes_in_float32(device):
    """bfloat16 in and out, float32 arithmetic and statistics: the output within one bfloat16 rounding of the float64
    result on the same bfloat16 input; the gradient of x within bfloat16 rounding of float64's, on the same
    bfloat16 gradient."""
    x = activations(2, 8, 9, 10, dtype=torch.bfloat16, device=device).requires_grad_()
    weight, bias, mean, var = affine(8, torch.float32, device)
    y = batch_norm_relu(x, weight, bias, mean, var)
    assert y.dtype == torch.bfloat16
    exact = x.detach().double().requires_grad_()
    params = [t.double() for t in affine(8, torch.float32, device)]
    expected = reference(exact, weight.double(), bias.double(), *params[2:])
    torch.testing.assert_close(y.double(), expected, rtol=2**-8, atol=1e-6)
    grad = torch.randn_like(expected).bfloat16()
    (mine,) = torch.autograd.grad(y, x, grad)
    (theirs,) = torch.autograd.grad(expected, exact, grad.double())
    assert mine.dtype == torch.bfloat16
    torch.testing.assert_close(mine.double(), theirs, rtol=2**-7, atol=2e-2)


def test_bfloat16_rounds_to_nearest_even():
    """The packed store rounds like torch's float32 -> bfloat16 cast: ties to even, NaN kept. An affine map that
    sends the batch to chosen float32 values (weight = std, bias = mean: the identity on x)."""
    values = torch.tensor([1.0, 1.0 + 2**-8, 1.0 + 3 * 2**-8, 1.0 + 2**-7 + 2**-9, -3.0, 7.5, 1e-3, 2.0])
    x = values.view(1, 2, 2, 2).bfloat16().contiguous(memory_format=torch.channels_last)
    assert torch.equal(x.float(), values.view(1, 2, 2, 2).bfloat16().float())  # the test's inputs are exact
    weight, bias, mean, var = affine(2, torch.float32)
    y = batch_norm_relu(x, weight, bias, mean, var)
    expected = reference(x.float(), weight, bias, mean.clone(), var.clone()).bfloat16()
    torch.testing.assert_close(y, expected, rtol=0, atol=0)


def test_gradcheck():
    x = activations(2, 4, 3, 3).requires_grad_()
    weight, bias, mean, var = affine(4)
    weight.requires_grad_()
    bias.requires_grad_()
    assert torch.autograd.gradcheck(lambda x, w, b: batch_norm_relu(x, w, b, mean, var), (x, weight, bias))
    # two rows per channel: the smallest batch with statistics
    pair = activations(2, 2, 1, 1).requires_grad_()
    params = affine(2)
    assert torch.autograd.gradcheck(lambda x: batch_norm_relu(x, *params), (pair,))


@pytest.mark.parametrize("device", device_params())
def test_backward_is_deterministic(device):
    x = activations(4, 8, 16, 16, dtype=torch.float32, device=device).requires_grad_()
    weight, bias, mean, var = affine(8, torch.float32, device)
    grad = torch.randn(4, 8, 16, 16, device=device)
    first, second = (torch.autograd.grad(batch_norm_relu(x, weight, bias, mean, var), x, grad)[0] for _ in range(2))
    assert torch.equal(first, second)


@pytest.mark.parametrize("device", device_params())
def test_module_norm_relu_matches_torch_module(device, monkeypatch):
    """`warpsense.models.dsunet.norm_relu` on a fused device: an nn.BatchNorm2d's output, running statistics and
    ``num_batches_tracked`` move as torch's own module moves them; in evaluation mode it is the module's forward."""
    from warpsense.models import dsunet

    monkeypatch.setattr(dsunet, "FUSED_DEVICES", (device,))
    mine, theirs = (torch.nn.BatchNorm2d(6).double().to(device) for _ in range(2))
    x = activations(2, 6, 5, 4, device=device)
    for _ in range(2):
        torch.testing.assert_close(dsunet.norm_relu(mine, x), torch.relu(theirs(x)), rtol=1e-12, atol=1e-12)
    for name, buffer in theirs.named_buffers():
        torch.testing.assert_close(dict(mine.named_buffers())[name], buffer, rtol=1e-12, atol=0)
    mine.eval()
    theirs.eval()
    torch.testing.assert_close(dsunet.norm_relu(mine, x), torch.relu(theirs(x)), rtol=1e-12, atol=1e-12)
