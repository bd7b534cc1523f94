import pytest
import torch
import torch.nn.functional as F

from warpsense.train.losses import edge_aware_smoothness, lovasz_softmax, ohem_cross_entropy


def test_ohem_keeps_hardest_fraction():
    logits = torch.zeros(1, 2, 1, 4)
    logits[0, 0, 0] = torch.tensor([4.0, 2.0, 0.0, -2.0])  # class-0 confidence falls along the row
    target = torch.zeros(1, 1, 4, dtype=torch.long)
    per_pixel = F.cross_entropy(logits, target, reduction="none").flatten()
    assert ohem_cross_entropy(logits, target, 0.5).item() == pytest.approx(per_pixel.sort().values[-2:].mean().item())
    assert ohem_cross_entropy(logits, target, 1.0).item() == pytest.approx(per_pixel.mean().item())
    target[0, 0, 3] = 255  # ignored pixels never count
    assert ohem_cross_entropy(logits, target, 0.34).item() == pytest.approx(per_pixel[2].item())


def test_lovasz_two_class_toy_by_hand():
    # 2 pixels, both class 1. p1 = (0.3, 0.6): errors for class 1: (0.7, 0.4) -> sorted (0.7, 0.4);
    # Jaccard gradient for gt = (1, 1): [1 - (2-1)/2, (1 - 0/2) - (1 - 1/2)] = [0.5, 0.5] -> 0.55.
    # class 0 is absent from the labels: not averaged in.
    probabilities = torch.tensor([[0.7, 0.3], [0.4, 0.6]])
    logits = probabilities.log().T.reshape(1, 2, 1, 2)
    target = torch.ones(1, 1, 2, dtype=torch.long)
    assert lovasz_softmax(logits, target).item() == pytest.approx(0.55, abs=1e-6)


def test_lovasz_perfect_prediction_zero_and_ignore():
    target = torch.tensor([[[0, 1, 1, 255]]])
    logits = F.one_hot(target.clamp(max=1), 2).permute(0, 3, 1, 2).float() * 50
    assert lovasz_softmax(logits, target).item() == pytest.approx(0.0, abs=1e-6)
    assert lovasz_softmax(logits, torch.full_like(target, 255)).item() == 0.0


def test_smoothness_lower_across_image_edges():
    logits = torch.zeros(1, 2, 4, 4)
    logits[0, 0, :, :2] = 5.0  # prediction changes between columns 1 and 2
    flat_guide = torch.zeros(1, 1, 4, 4)
    edge_guide = flat_guide.clone()
    edge_guide[..., 2:] = 1.0  # an image edge at the same place
    assert edge_aware_smoothness(logits, edge_guide) < 0.01 * edge_aware_smoothness(logits, flat_guide)


def test_lovasz_grad_equals_the_papers_algorithm_row_by_row():
    """Berman et al. 2018, alg. 1, per row in NumPy: the flattened int32 running count must give each row's own."""
    import numpy as np

    from warpsense.ops.reference import lovasz_grad

    generator = torch.Generator().manual_seed(3)
    labels = (torch.rand(2, 5, 257, generator=generator) < 0.3).float()
    labels[0, 1] = 0  # a class absent from the batch
    labels[1, 2] = 1  # a class everywhere
    expected = np.empty(labels.shape)
    for index in np.ndindex(labels.shape[:-1]):
        row = labels[index].numpy().astype(np.float64)
        gts = row.sum()
        jaccard = 1 - (gts - np.cumsum(row)) / (gts + np.cumsum(1 - row))
        expected[index] = np.concatenate([jaccard[:1], np.diff(jaccard)])
    np.testing.assert_allclose(lovasz_grad(labels).numpy(), expected, atol=1e-6)
    np.testing.assert_allclose(lovasz_grad(labels.double()).numpy(), expected, atol=1e-12)


def test_distillation_loss_against_a_numpy_kl():
    """T^2 mean over pixels of sum_k p_t (log p_t - log p_s), with p = softmax(logits / T), against NumPy."""
    import numpy as np

    from warpsense.train.losses import distillation_loss

    torch.manual_seed(0)
    student, teacher = torch.randn(2, 5, 3, 4, dtype=torch.float64), 3 * torch.randn(2, 5, 3, 4, dtype=torch.float64)
    for temperature in (1.0, 2.5):
        s, t = student.numpy() / temperature, teacher.numpy() / temperature
        log_s = s - np.log(np.exp(s).sum(axis=1, keepdims=True))
        log_t = t - np.log(np.exp(t).sum(axis=1, keepdims=True))
        expected = temperature**2 * (np.exp(log_t) * (log_t - log_s)).sum(axis=1).mean()
        assert distillation_loss(student, teacher, temperature).item() == pytest.approx(expected, rel=1e-5)


def test_distillation_loss_zero_at_the_teacher_and_gradient_to_the_student_only():
    from warpsense.train.losses import distillation_loss

    teacher = torch.randn(1, 4, 5, 5, requires_grad=True)
    assert distillation_loss(teacher.detach().clone(), teacher).abs().item() < 1e-6
    student = torch.zeros(1, 4, 5, 5, requires_grad=True)
    distillation_loss(student, teacher).backward()
    assert teacher.grad is None and student.grad.abs().sum() > 0
    # the gradient is (p_s - p_t) / pixels: it pulls the student's probabilities towards the teacher's
    expected = (torch.softmax(student, 1) - torch.softmax(teacher, 1)).detach() / 25
    torch.testing.assert_close(student.grad, expected, rtol=1e-5, atol=1e-7)


def test_distillation_ignores_what_its_softmax_ignores():
    """Pixel-wise distillation normalises over the classes, so a constant added to every class at a pixel changes
    nothing; a constant added to a whole class map does change it."""
    from warpsense.train.losses import distillation_loss

    torch.manual_seed(2)
    teacher = torch.randn(2, 4, 5, 6, dtype=torch.float64)
    per_pixel = teacher + 3 * torch.randn(2, 1, 5, 6, dtype=torch.float64)
    per_class = teacher + 3 * torch.randn(2, 4, 1, 1, dtype=torch.float64)
    assert distillation_loss(per_pixel, teacher, 2.0, "pixel").item() < 1e-12
    assert distillation_loss(per_class, teacher, 2.0, "pixel").item() > 1e-3


def test_distillation_gradcheck():
    from warpsense.train.losses import distillation_loss

    torch.manual_seed(3)
    teacher = torch.randn(1, 3, 4, 5, dtype=torch.float64)
    student = torch.randn(1, 3, 4, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: distillation_loss(x, teacher, 1.7, "pixel"), (student,))


def test_distillation_mode_unknown_lists_the_valid_ones():
    from warpsense.train.losses import distillation_loss

    for mode in ("spatial", "channel"):  # channel: retired (the config refuses it, warpsense.config.RETIRED_VALUES)
        with pytest.raises(KeyError, match=f"unknown distillation mode '{mode}'; valid: pixel\"$"):
            distillation_loss(torch.zeros(1, 2, 2, 2), torch.zeros(1, 2, 2, 2), 1.0, mode)


def test_segmentation_loss_is_the_weighted_sum_of_its_terms():
    # the terms share one softmax inside segmentation_loss: the total and its gradient are those of the public
    # term functions, each computing its own
    from warpsense.config import load_config
    from warpsense.train.losses import segmentation_loss

    generator = torch.Generator().manual_seed(1)
    logits = torch.randn(2, 5, 6, 8, generator=generator, dtype=torch.float64)
    target = torch.randint(0, 5, (2, 6, 8), generator=generator)
    target[1, 2, 3] = 255
    guide = torch.rand(2, 3, 6, 8, generator=generator)
    config = load_config(None, []).loss
    mine = logits.clone().requires_grad_()
    total, parts = segmentation_loss(mine, target, guide, config)
    theirs = logits.clone().requires_grad_()
    expected = (config.ohem_weight * ohem_cross_entropy(theirs, target, config.ohem_fraction)
                + config.lovasz_weight * lovasz_softmax(theirs, target)
                + config.smooth_weight * edge_aware_smoothness(theirs, guide))
    torch.testing.assert_close(total, expected.float())
    assert set(parts) == {"ohem", "lovasz", "smooth"}
    total.backward()
    expected.backward()
    torch.testing.assert_close(mine.grad, theirs.grad, rtol=1e-5, atol=1e-7)
