"""The Lovasz-softmax op (one sort of all classes) against its plain-torch reference, a NumPy transcription of the
paper's algorithm, and known answers."""

import numpy as np
import pytest
import torch

from tests.conftest import assert_matches_reference, device_params
from warpsense.ops.lovasz import MAX_CLASSES, level_bits, lovasz_softmax
from warpsense.ops.reference import lovasz_softmax_reference
from warpsense.train import losses


def _inputs(batch=2, classes=4, height=5, width=6, dtype=torch.float64, device="cpu", ignored=3, seed=0):
    generator = torch.Generator().manual_seed(seed)
    probabilities = torch.softmax(3 * torch.randn(batch, classes, height, width, generator=generator, dtype=dtype), 1)
    labels = torch.randint(0, classes, (batch, height, width), generator=generator)
    labels.view(-1)[torch.randperm(labels.numel(), generator=generator)[:ignored]] = 255
    return probabilities.to(device).requires_grad_(), labels.to(device)


def _numpy_lovasz(probabilities: np.ndarray, labels: np.ndarray, ignore_index=255) -> float:
    """Berman et al. 2018, alg. 1 per class, in float64 NumPy: the mean over present classes of <sorted errors,
    Lovasz gradient>."""
    losses = []
    valid = labels != ignore_index
    for c in range(probabilities.shape[1]):
        fg = ((labels == c) & valid).astype(np.float64).ravel()
        if fg.sum() == 0:
            continue
        errors = (np.abs(fg - probabilities[:, c].ravel()) * valid.ravel())
        order = np.argsort(-errors, kind="stable")
        sorted_fg = fg[order]
        gts = sorted_fg.sum()
        jaccard = 1 - (gts - np.cumsum(sorted_fg)) / (gts + np.cumsum(1 - sorted_fg))
        losses.append(errors[order] @ np.concatenate([jaccard[:1], np.diff(jaccard)]))
    return float(np.mean(losses)) if losses else 0.0


@pytest.mark.parametrize("device", device_params())
def test_smoke(device):
    probabilities, labels = _inputs(device=device)
    loss = lovasz_softmax(probabilities, labels)
    assert loss.shape == () and loss.device.type == device and loss.dtype == torch.float64 and 0 < loss < 1


def test_exception():
    probabilities, labels = _inputs()
    with pytest.raises(ValueError, match="labels must be"):
        lovasz_softmax(probabilities, labels[:, :4])
    with pytest.raises(TypeError, match="integer"):
        lovasz_softmax(probabilities, labels.double())
    with pytest.raises(ValueError, match=r"\[B, K, H, W\]"):
        lovasz_softmax(probabilities[0], labels)
    with pytest.raises(ValueError, match=f"at most {MAX_CLASSES} classes"):
        lovasz_softmax(torch.rand(1, MAX_CLASSES + 1, 2, 2), torch.zeros(1, 2, 2, dtype=torch.long))
    # ignore_index went through int(): None was "int() argument must be ...", a float was truncated
    for bad in (None, 2.0, True):
        with pytest.raises(TypeError, match=f"^lovasz_softmax: ignore_index must be an int, got {type(bad).__name__}"):
            lovasz_softmax(probabilities, labels, bad)
    with pytest.raises(ValueError, match="^lovasz_softmax: ignore_index must fit in int32"):
        lovasz_softmax(probabilities, labels, 2**40)
    assert lovasz_softmax(probabilities, labels, np.int64(255)) == lovasz_softmax(probabilities, labels, 255)


@pytest.mark.parametrize("shape", [(1, 1, 1, 1), (2, 11, 3, 7), (3, 2, 6, 1), (1, 3, 70, 2)])
def test_cardinality(shape):
    batch, classes, height, width = shape
    probabilities, labels = _inputs(batch, classes, height, width, ignored=0)
    loss = lovasz_softmax(probabilities, labels)
    (grad,) = torch.autograd.grad(loss, probabilities)
    assert loss.shape == () and grad.shape == shape


@pytest.mark.parametrize("device", device_params())
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(2, 4, 5, 6), (3, 11, 9, 13), (1, 19, 4, 40)])
def test_feature_vs_reference(device, dtype, shape):
    # (1, 19, 4, 40): Cityscapes' classes, 160 pixels: chunks of 64 keys end inside a class and at its end
    probabilities, labels = _inputs(*shape, dtype=dtype, device=device)
    assert_matches_reference(lovasz_softmax, lovasz_softmax_reference, (probabilities, labels),
                             torch.tensor(1.3, dtype=dtype, device=device))


def test_feature_vs_the_papers_algorithm_in_numpy():
    for seed in range(3):
        probabilities, labels = _inputs(3, 6, 7, 9, ignored=10, seed=seed)
        wanted = _numpy_lovasz(probabilities.detach().numpy(), labels.numpy())
        assert lovasz_softmax(probabilities, labels).item() == pytest.approx(wanted, rel=1e-12)


def test_feature_known_answers():
    labels = torch.tensor([[[0, 0, 1, 1]]])
    perfect = torch.nn.functional.one_hot(labels, 2).permute(0, 3, 1, 2).double()
    assert lovasz_softmax(perfect, labels) == 0
    assert lovasz_softmax(perfect, torch.full_like(labels, 255)) == 0  # nothing labelled
    # both classes at probability 1/2 everywhere: every error is 1/2, so each class's loss is 1/2 J_P = 1/2
    assert lovasz_softmax(torch.full((1, 2, 1, 4), 0.5, dtype=torch.float64), labels).item() == pytest.approx(0.5)
    # a class absent from the labels does not count: a third class with probability 0 leaves the mean over two
    three = torch.cat([torch.full((1, 2, 1, 4), 0.5, dtype=torch.float64), torch.zeros(1, 1, 1, 4,
                                                                                        dtype=torch.float64)], 1)
    assert lovasz_softmax(three, labels).item() == pytest.approx(0.5)


def test_feature_ties_have_the_loss_of_any_order():
    # equal errors: the loss sums e times the gradients of a tie group, which add to the same J difference in any
    # order; a pixel at probability exactly 1 of its class (error 0) has gradient 0, as |.| has in torch
    probabilities, labels = _inputs(2, 3, 4, 5, ignored=0)
    with torch.no_grad():
        probabilities[:, :, :2] = 1 / 3
        probabilities[0, :, 3, 4] = torch.nn.functional.one_hot(labels[0, 3, 4], 3).double()
    torch.testing.assert_close(lovasz_softmax(probabilities, labels), lovasz_softmax_reference(probabilities,
                                                                                               labels))
    (grad,) = torch.autograd.grad(lovasz_softmax(probabilities, labels), probabilities)
    assert grad[0, labels[0, 3, 4], 3, 4] == 0


def test_feature_errors_closer_than_a_level_move_the_loss_by_at_most_a_level():
    # 11 classes: errors are ranked by levels of 2^-25; pixels whose errors differ by less may be ranked either way
    probabilities, labels = _inputs(1, 11, 6, 8, ignored=0)
    with torch.no_grad():
        probabilities += 2.0**-28 * torch.rand_like(probabilities)
    bound = 2.0 ** -level_bits(11)
    assert level_bits(11) == 25
    assert abs(lovasz_softmax(probabilities, labels) - lovasz_softmax_reference(probabilities, labels)) <= bound


def test_feature_strided_and_channels_last_views_are_read_in_place():
    probabilities, labels = _inputs(2, 5, 8, 10)
    nhwc = probabilities.detach().to(memory_format=torch.channels_last).requires_grad_()
    strided_labels = labels[..., ::2, ::3]
    assert_matches_reference(lambda p, t: lovasz_softmax(p[..., ::2, ::3], t),
                             lambda p, t: lovasz_softmax_reference(p[..., ::2, ::3].contiguous(), t.contiguous()),
                             (nhwc, strided_labels), torch.tensor(1.0, dtype=torch.float64))


@pytest.mark.parametrize("device", device_params())
def test_backward_is_deterministic(device):
    probabilities, labels = _inputs(2, 11, 24, 32, dtype=torch.float32, device=device)
    runs = [torch.autograd.grad(lovasz_softmax(probabilities, labels), probabilities)[0] for _ in range(2)]
    assert torch.equal(*runs)


def test_gradcheck():
    probabilities, labels = _inputs(2, 3, 4, 5)
    assert torch.autograd.gradcheck(lambda p: lovasz_softmax(p, labels), (probabilities,))


def test_module_loss_term_takes_the_op_unless_switched_off(monkeypatch):
    """The training loss's Lovasz term runs the fused op on a `FUSED_LOSS_DEVICES` device (the CPU here), and its
    plain-torch reference within `LOSS_OPS.torch_ops("lovasz")` (the benchmarks' baseline): the same function."""
    calls = []
    monkeypatch.setattr(losses, "FUSED_LOSS_DEVICES", ("cpu",))
    monkeypatch.setattr(losses, "fused_lovasz", lambda *args: calls.append("fused") or lovasz_softmax(*args))
    logits = torch.randn(2, 5, 6, 7, dtype=torch.float64, requires_grad=True)
    labels = torch.randint(0, 5, (2, 6, 7))
    fused = losses.lovasz_softmax(logits, labels)
    assert calls == ["fused"]
    with losses.LOSS_OPS.torch_ops("lovasz"):
        plain = losses.lovasz_softmax(logits, labels)
    assert calls == ["fused"]
    torch.testing.assert_close(fused, plain)
    torch.testing.assert_close(torch.autograd.grad(fused, logits)[0], torch.autograd.grad(plain, logits)[0])
    with pytest.raises(KeyError, match="valid: softmax, lovasz, smoothness"):
        with losses.LOSS_OPS.torch_ops("ohem"):
            pass
