"""The fused edge-aware smoothness op (eq. 9 of the paper) against its plain-torch reference, with known answers."""

import pytest
import torch

from tests.conftest import assert_matches_reference, device_params
from warpsense.ops.reference import edge_aware_smoothness_reference
from warpsense.ops.smoothness import edge_aware_smoothness
from warpsense.train.losses import LOSS_OPS
from warpsense.train.losses import edge_aware_smoothness as smoothness_loss


def _inputs(batch=2, classes=4, height=5, width=6, dtype=torch.float64, device="cpu"):
    probabilities = torch.softmax(torch.randn(batch, classes, height, width, dtype=dtype), dim=1)
    guide = torch.rand(batch, height, width, dtype=dtype)
    return probabilities.to(device).requires_grad_(), guide.to(device).requires_grad_()


@pytest.mark.parametrize("device", device_params())
def test_smoke(device):
    probabilities, guide = _inputs(device=device)
    out = edge_aware_smoothness(probabilities, guide, 0.1)
    assert out.shape == () and out.device.type == device and out.dtype == torch.float64 and out > 0


def test_exception():
    probabilities, guide = _inputs()
    with pytest.raises(ValueError, match="guide must be"):
        edge_aware_smoothness(probabilities, guide[:, :4])
    with pytest.raises(ValueError, match=r"\[B, K, H, W\]"):
        edge_aware_smoothness(probabilities[0], guide)
    with pytest.raises(ValueError, match="2 x 2"):
        edge_aware_smoothness(probabilities[..., :1], guide[..., :1])
    with pytest.raises(ValueError, match="sigma"):
        edge_aware_smoothness(probabilities, guide, 0.0)
    with pytest.raises(ValueError, match="sigma"):
        edge_aware_smoothness(probabilities, guide, float("nan"))


@pytest.mark.parametrize("shape", [(1, 1, 2, 2), (2, 11, 3, 7), (3, 2, 6, 2)])
def test_cardinality(shape):
    batch, classes, height, width = shape
    probabilities, guide = _inputs(batch, classes, height, width)
    out = edge_aware_smoothness(probabilities, guide)
    grads = torch.autograd.grad(out, (probabilities, guide))
    assert out.shape == () and grads[0].shape == shape and grads[1].shape == (batch, height, width)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sigma", [0.05, 1.0])
def test_feature_vs_reference(dtype, sigma):
    probabilities, guide = _inputs(2, 5, 6, 7, dtype=dtype)
    assert_matches_reference(lambda p, g: edge_aware_smoothness(p, g, sigma),
                             lambda p, g: edge_aware_smoothness_reference(p, g, sigma), (probabilities, guide),
                             torch.tensor(1.7, dtype=dtype))


def test_feature_ties_have_the_gradient_of_torchs_abs():
    # a flat guide (clipped or quantized neighbours are equal) and equal probabilities: |0| has gradient 0 in torch
    probabilities, guide = _inputs(2, 3, 4, 5)
    with torch.no_grad():
        guide[:, :, :3] = 0.25
        probabilities[:, :, 1:, 1:3] = probabilities[:, :, 1:2, 1:2]
    assert_matches_reference(edge_aware_smoothness, edge_aware_smoothness_reference, (probabilities, guide),
                             torch.tensor(1.0, dtype=torch.float64))


def test_feature_known_answers():
    # constant probabilities: no pair differs, the loss is 0 whatever the guide
    flat = torch.full((1, 3, 4, 4), 1 / 3, dtype=torch.float64)
    assert edge_aware_smoothness(flat, torch.rand(1, 4, 4, dtype=torch.float64)) == 0
    # a vertical class boundary between columns 1 and 2 of a 4x4 image and a flat guide: the 4 horizontal pairs
    # across it differ by |1 - 0| + |0 - 1| = 2 with weight 1, of 12 horizontal pairs; no vertical pair differs
    step = torch.zeros(1, 2, 4, 4, dtype=torch.float64)
    step[:, 0, :, :2] = 1
    step[:, 1, :, 2:] = 1
    guide = torch.zeros(1, 4, 4, dtype=torch.float64)
    torch.testing.assert_close(edge_aware_smoothness(step, guide), torch.tensor(0.5 * 4 * 2 / 12, dtype=torch.float64))
    # the same boundary on an image edge of height 1 in the guide: weight exp(-1 / sigma) across it
    guide[..., 2:] = 1.0
    expected = 0.5 * 4 * 2 * torch.exp(torch.tensor(-2.0)).item() / 12
    torch.testing.assert_close(edge_aware_smoothness(step, guide, sigma=0.5),
                               torch.tensor(expected, dtype=torch.float64))


def test_feature_channels_last_is_read_in_place():
    probabilities, guide = _inputs(2, 4, 5, 6)
    nhwc = probabilities.detach().to(memory_format=torch.channels_last).requires_grad_()
    torch.testing.assert_close(edge_aware_smoothness(nhwc, guide), edge_aware_smoothness(probabilities, guide))
    (grad,) = torch.autograd.grad(edge_aware_smoothness(nhwc, guide), nhwc)
    (wanted,) = torch.autograd.grad(edge_aware_smoothness_reference(probabilities, guide), probabilities)
    torch.testing.assert_close(grad, wanted)


def test_gradcheck():
    probabilities, guide = _inputs(2, 3, 4, 5)
    assert torch.autograd.gradcheck(lambda p, g: edge_aware_smoothness(p, g, 0.3), (probabilities, guide))


@pytest.mark.parametrize("device", device_params())
def test_module_loss_term_equals_the_plain_torch_formula(device):
    # the training loss's term (softmax of logits, guide channel mean, resized) with the fused pairs and with the
    # plain-torch ones: the baseline's loss and the recipe's are the same function
    logits = torch.randn(2, 5, 8, 10, dtype=torch.float64, device=device, requires_grad=True)
    guide = torch.rand(2, 3, 4, 5, dtype=torch.float64, device=device, requires_grad=True)
    fused = smoothness_loss(logits, guide)
    with LOSS_OPS.torch_ops("smoothness"):
        plain = smoothness_loss(logits, guide)
    torch.testing.assert_close(fused, plain.float())
    grads = torch.autograd.grad(fused, (logits, guide))
    wanted = torch.autograd.grad(plain, (logits, guide))
    for a, b in zip(grads, wanted):
        torch.testing.assert_close(a.double(), b.double(), rtol=1e-5, atol=1e-7)
