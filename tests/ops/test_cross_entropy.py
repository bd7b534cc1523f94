"""The fused softmax + per-pixel cross-entropy op against torch's log_softmax / nll_loss and softmax, and the training
loss with it against the loss with torch's."""

import pytest
import torch
from torch.nn import functional as F

from tests.conftest import device_params
from warpsense.config import load_config
from warpsense.ops.cross_entropy import softmax_cross_entropy
from warpsense.train import losses


def _inputs(batch=2, classes=5, height=4, width=6, dtype=torch.float64, device="cpu", layout="channels_last"):
    generator = torch.Generator().manual_seed(0)
    logits = 3 * torch.randn(batch, classes, height, width, generator=generator, dtype=torch.float64)
    logits = logits.to(dtype).to(memory_format=getattr(torch, layout + "_format") if layout != "channels_last"
                                 else torch.channels_last)
    labels = torch.randint(0, classes, (batch, height, width), generator=generator)
    labels[0, 0, :2] = 255
    return logits.to(device).requires_grad_(), labels.to(device)


def _reference(logits, labels, weights=None):
    arithmetic = logits if logits.dtype == torch.float64 else logits.float()
    weight = None if weights is None else weights.to(arithmetic.dtype)
    return (F.cross_entropy(arithmetic, labels, weight=weight, ignore_index=255, reduction="none"),
            torch.softmax(arithmetic, dim=1))


def _gradient(function, logits, labels, grads):
    outputs = function(logits, labels)
    return torch.autograd.grad(sum((out * grad).sum() for out, grad in zip(outputs, grads)), logits)[0]


@pytest.mark.parametrize("device", device_params())
def test_smoke(device):
    logits, labels = _inputs(device=device)
    pixel_losses, probabilities = softmax_cross_entropy(logits, labels)
    assert pixel_losses.shape == labels.shape and probabilities.shape == logits.shape
    assert pixel_losses.device.type == device and probabilities.dtype == torch.float64


def test_exception():
    logits, labels = _inputs()
    with pytest.raises(ValueError, match="labels must be"):
        softmax_cross_entropy(logits, labels[:, :3])
    with pytest.raises(TypeError, match="integer"):
        softmax_cross_entropy(logits, labels.double())
    with pytest.raises(ValueError, match=r"weights must be \[K\]"):
        softmax_cross_entropy(logits, labels, torch.ones(4))
    with pytest.raises(ValueError, match=r"\[B, K, H, W\]"):
        softmax_cross_entropy(logits[0], labels)
    # a list of weights failed on weights.shape (AttributeError); ignore_index None in int()
    with pytest.raises(TypeError, match=r"^softmax_cross_entropy: weights must be a \[K\] tensor or None, got list"):
        softmax_cross_entropy(logits, labels, [1.0] * logits.shape[1])
    with pytest.raises(TypeError, match="^softmax_cross_entropy: ignore_index must be an int, got NoneType"):
        softmax_cross_entropy(logits, labels, ignore_index=None)


@pytest.mark.parametrize("shape", [(1, 1, 1, 1), (2, 11, 3, 7), (3, 2, 5, 1)])
def test_cardinality(shape):
    logits, labels = _inputs(*shape)
    pixel_losses, probabilities = softmax_cross_entropy(logits, labels)
    (grad,) = torch.autograd.grad(pixel_losses.sum() + probabilities.square().sum(), logits)
    assert pixel_losses.shape == (shape[0], *shape[2:]) and probabilities.shape == shape and grad.shape == shape


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("layout", ["channels_last", "contiguous"])
@pytest.mark.parametrize("weighted", [False, True])
def test_feature_vs_reference(device, dtype, layout, weighted):
    logits, labels = _inputs(2, 11, 5, 7, dtype=dtype, device=device, layout=layout)
    weights = torch.rand(11, dtype=dtype, device=device) + 0.5 if weighted else None
    mine, theirs = softmax_cross_entropy(logits, labels, weights), _reference(logits, labels, weights)
    for a, b in zip(mine, theirs):
        torch.testing.assert_close(a, b)
    grads = [torch.randn_like(t) for t in theirs]
    grad = _gradient(lambda z, t: softmax_cross_entropy(z, t, weights), logits, labels, grads)
    torch.testing.assert_close(grad, _gradient(lambda z, t: _reference(z, t, weights), logits, labels, grads))
    assert grad.is_contiguous(memory_format=torch.channels_last) == (layout == "channels_last")


@pytest.mark.parametrize("device", device_params())
def test_bfloat16_computes_in_float32(device):
    logits, labels = _inputs(2, 11, 6, 8, dtype=torch.bfloat16, device=device)
    mine, theirs = softmax_cross_entropy(logits, labels), _reference(logits, labels)
    assert mine[1].dtype == torch.float32
    for a, b in zip(mine, theirs):
        torch.testing.assert_close(a, b)
    grads = [torch.randn_like(t) for t in theirs]
    grad = _gradient(softmax_cross_entropy, logits, labels, grads)
    wanted = _gradient(_reference, logits, labels, grads)
    assert grad.dtype == torch.bfloat16
    # the float32 gradient rounded once to bf16 either way: within two of its units in the last place
    assert ((grad.float() - wanted.float()).abs() <= 2 * 2.0**-8 * wanted.float().abs() + 1e-30).all()


def test_feature_known_answers():
    # equal logits: probabilities 1/K, each labelled pixel's loss log K, an ignored one 0
    logits = torch.zeros(1, 4, 1, 2, dtype=torch.float64)
    pixel_losses, probabilities = softmax_cross_entropy(logits, torch.tensor([[[2, 255]]]))
    torch.testing.assert_close(probabilities, torch.full_like(logits, 0.25))
    torch.testing.assert_close(pixel_losses, torch.tensor([[[torch.log(torch.tensor(4.0)).item(), 0.0]]],
                                                          dtype=torch.float64))
    # logits 1000 apart: exp would overflow without the max shifted out
    far = torch.tensor([[[[1000.0]], [[0.0]]]], dtype=torch.float32)
    pixel_losses, probabilities = softmax_cross_entropy(far, torch.tensor([[[1]]]))
    assert pixel_losses.item() == 1000.0 and probabilities[0, :, 0, 0].tolist() == [1.0, 0.0]


@pytest.mark.parametrize("device", device_params())
def test_backward_is_deterministic(device):
    logits, labels = _inputs(2, 11, 16, 24, dtype=torch.float32, device=device)
    grads = [torch.randn(2, 16, 24, device=device), torch.randn(2, 11, 16, 24, device=device)]
    runs = [_gradient(softmax_cross_entropy, logits, labels, grads) for _ in range(2)]
    assert torch.equal(*runs)


def test_gradcheck():
    logits, labels = _inputs(2, 3, 3, 4)
    weights = torch.rand(3, dtype=torch.float64) + 0.5
    assert torch.autograd.gradcheck(lambda z: softmax_cross_entropy(z, labels, weights), (logits,))


def test_module_training_loss_with_the_op_equals_torchs(monkeypatch):
    """The recipe's loss (OHEM + Lovasz + smoothness) with the fused softmax and cross-entropy (on a
    `FUSED_LOSS_DEVICES` device: the CPU here) equals the loss with torch's, value and gradient."""
    monkeypatch.setattr(losses, "FUSED_LOSS_DEVICES", ("cpu",))
    calls = []
    monkeypatch.setattr(losses, "softmax_cross_entropy",
                        lambda *args, **kwargs: calls.append(1) or softmax_cross_entropy(*args, **kwargs))
    logits, labels = _inputs(2, 5, 8, 10, dtype=torch.float32)  # the loss is float32 (float64 logits: torch's
    guide = torch.rand(2, 3, 8, 10)                               # form casts them down, the op keeps float64)
    config = load_config(None, []).loss
    with losses.LOSS_OPS.torch_ops("lovasz"):  # the fused Lovasz op is on too; only the softmax differs
        fused, _ = losses.segmentation_loss(logits, labels, guide, config)
        assert calls == [1]
        with losses.LOSS_OPS.torch_ops("softmax"):
            plain, _ = losses.segmentation_loss(logits, labels, guide, config)
    assert calls == [1]
    torch.testing.assert_close(fused, plain)
    torch.testing.assert_close(torch.autograd.grad(fused, logits)[0], torch.autograd.grad(plain, logits)[0])
