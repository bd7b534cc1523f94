"""Segmentation losses of eqs. 7-10 of the paper (docs/references.md): OHEM cross-entropy, Lovasz-softmax, edge-aware
smoothness."""

from __future__ import annotations

import torch
from torch.nn import functional as F

from warpsense.data.labels import IGNORE_INDEX
from warpsense.ops.cross_entropy import softmax_cross_entropy
from warpsense.ops.lovasz import MAX_CLASSES
from warpsense.ops.lovasz import lovasz_softmax as fused_lovasz
from warpsense.ops.reference import edge_aware_smoothness_reference, lovasz_softmax_reference
from warpsense.ops.smoothness import edge_aware_smoothness as fused_smoothness
from warpsense.ops.switch import OpSwitch


def ohem_cross_entropy(logits: torch.Tensor, target: torch.Tensor, fraction: float = 0.25,
                       ignore_index: int = IGNORE_INDEX) -> torch.Tensor:
    """Mean cross-entropy over the hardest ``fraction`` of the valid pixels (eq. 7 of the paper).

    Computed without a host round trip (the number of valid pixels stays on the device): the losses are ranked
    by a sort and the first round(fraction * valid) kept. Returns 0 when no pixel is valid.

    Args:
        logits: [B, K, H, W]; target: [B, H, W] class indices, ``ignore_index`` excluded.
        fraction: share of valid pixels kept (at least one); 1.0 is plain cross-entropy.
    """
    losses = F.cross_entropy(logits.float(), target, ignore_index=ignore_index, reduction="none")
    return hardest_mean(losses, target, fraction, ignore_index)


def hardest_mean(losses: torch.Tensor, target: torch.Tensor, fraction: float = 0.25,
                 ignore_index: int = IGNORE_INDEX) -> torch.Tensor:
    """The mean of the largest ``fraction`` of per-pixel losses [B, H, W] over the valid pixels of ``target``
    [B, H, W] (`ohem_cross_entropy`'s selection; at least one pixel; 1.0: the mean over all valid ones)."""
    losses = losses.flatten()
    valid = target.flatten() != ignore_index
    count = valid.sum()
    if fraction >= 1.0:
        return losses.sum() / count.clamp_min(1)
    keep = torch.round(fraction * count).clamp_min(1)
    ranked = torch.where(valid, losses, 0.0).sort(descending=True).values
    kept = torch.arange(ranked.numel(), device=ranked.device) < keep
    return (ranked * kept).sum() / keep


LOSS_OPS = OpSwitch(("softmax", "lovasz", "smoothness"))
"""The loss's Warp ops, by name: the softmax and the OHEM term's per-pixel cross-entropy in one pass
(`warpsense.ops.softmax_cross_entropy`), the Lovasz term from one sort of all classes
(`warpsense.ops.lovasz_softmax`) and the edge-aware smoothness term in one pass
(`warpsense.ops.edge_aware_smoothness`). Within ``LOSS_OPS.torch_ops`` they run as torch's own ops and the
plain-torch references (`warpsense.ops.reference`), as in the benchmarks' plain-torch baseline."""
FUSED_LOSS_DEVICES = ("cuda",)
"""Devices where the softmax with cross-entropy and the Lovasz term take their fused ops (the smoothness op runs
everywhere): on a CPU the Lovasz op's tiles run as Warp's cooperative fibers, far slower than torch's sort there,
and Warp's CPU kernels use one core where torch's use all."""


def lovasz_softmax(logits: torch.Tensor, target: torch.Tensor, ignore_index: int = IGNORE_INDEX) -> torch.Tensor:
    """Lovasz-softmax loss (Berman, Rannen Triki, Blaschko, CVPR 2018) of logits [B, K, H, W] and labels [B, H, W],
    averaged over the classes present in the batch's labels (no host round trip). Returns 0 when no pixel is
    valid."""
    return _lovasz_of_probabilities(torch.softmax(logits.float(), dim=1), target, ignore_index)


def _lovasz_of_probabilities(probabilities: torch.Tensor, target: torch.Tensor,
                             ignore_index: int = IGNORE_INDEX) -> torch.Tensor:
    """`lovasz_softmax` of class probabilities [B, K, H, W]: the fused op on a `FUSED_LOSS_DEVICES` device (up to
    `MAX_CLASSES` classes) unless `LOSS_OPS` has it off."""
    if (LOSS_OPS.fused("lovasz") and probabilities.device.type in FUSED_LOSS_DEVICES
            and probabilities.shape[1] <= MAX_CLASSES):
        return fused_lovasz(probabilities, target, ignore_index)
    return lovasz_softmax_reference(probabilities, target, ignore_index)


def edge_aware_smoothness(logits: torch.Tensor, guide: torch.Tensor, sigma: float = 0.1) -> torch.Tensor:
    """Mean over 4-neighbour pairs of w_pq |P(p) - P(q)|_1 (eq. 9 of the paper), w_pq = exp(-|I_p - I_q| / sigma)
    from the guide image [B, C, H, W] (the sensor output; its channel mean, resized to the logits if needed), so
    predictions stay smooth except across image edges: one fused Warp op forward and backward
    (`warpsense.ops.smoothness`) unless `LOSS_OPS` has it off."""
    return _smoothness_of_probabilities(torch.softmax(logits.float(), dim=1), guide, sigma)


def _smoothness_of_probabilities(probabilities: torch.Tensor, guide: torch.Tensor, sigma: float = 0.1) -> torch.Tensor:
    """`edge_aware_smoothness` of class probabilities [B, K, H, W]."""
    guide = guide.float().mean(dim=1, keepdim=True)
    if guide.shape[-2:] != probabilities.shape[-2:]:
        guide = F.interpolate(guide, size=probabilities.shape[-2:], mode="bilinear", align_corners=False)
    pairs = fused_smoothness if LOSS_OPS.fused("smoothness") else edge_aware_smoothness_reference
    return pairs(probabilities, guide[:, 0], sigma)


def pixel_distillation(student: torch.Tensor, teacher: torch.Tensor, temperature: float = 1.0) -> torch.Tensor:
    """Pixel-wise knowledge distillation (Hinton et al. 2015; per pixel as in Liu et al., CVPR 2019): the mean over
    pixels of T^2 KL(softmax(teacher / T) || softmax(student / T)), the softmax over the classes. The T^2 keeps its
    gradients' scale independent of T. Every pixel counts, labelled or not: the teacher has an answer for void
    pixels too.

    Args:
        student: [B, K, H, W] logits being trained; teacher: [B, K, H, W] logits (no gradient flows into them).
        temperature: T > 0.
    """
    return _kl_over(student, teacher, temperature, dim=1).mean()


def _kl_over(student: torch.Tensor, teacher: torch.Tensor, temperature: float, dim: int) -> torch.Tensor:
    """T^2 KL(softmax(teacher / T) || softmax(student / T)) with both softmaxes along ``dim`` (float32 or wider)."""
    dtype = torch.promote_types(student.dtype, torch.float32)
    log_student = torch.log_softmax(student.to(dtype) / temperature, dim=dim)
    log_teacher = torch.log_softmax(teacher.detach().to(dtype) / temperature, dim=dim)
    return temperature**2 * (log_teacher.exp() * (log_teacher - log_student)).sum(dim=dim)


DISTILLATION = {"pixel": pixel_distillation}
"""The distillation terms by `loss.distill_mode` (names: `warpsense.choices.DISTILL_MODES`)."""


def distillation_loss(student: torch.Tensor, teacher: torch.Tensor, temperature: float = 1.0,
                      mode: str = "pixel") -> torch.Tensor:
    """The distillation term of ``mode`` (`DISTILLATION`): ``student`` and ``teacher`` logits [B, K, H, W]."""
    try:
        term = DISTILLATION[mode]
    except KeyError:
        raise KeyError(f"unknown distillation mode {mode!r}; valid: {', '.join(DISTILLATION)}") from None
    return term(student, teacher, temperature)


def segmentation_loss(logits, target, guide, loss_config) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss 0.6 OHEM + 0.4 Lovasz + lambda smoothness (eq. 10 of the paper; weights from the config).

    Returns the loss and a dict of its detached parts (tensors: no host sync per step)."""
    parts = {}
    total = logits.new_zeros((), dtype=torch.float32)
    # one softmax for the two terms that read probabilities
    needs_probabilities = loss_config.lovasz_weight > 0 or loss_config.smooth_weight > 0
    if (loss_config.ohem_weight > 0 and needs_probabilities and LOSS_OPS.fused("softmax")
            and logits.device.type in FUSED_LOSS_DEVICES):
        # both from one pass over the (bf16) logits, and one backward into them
        pixel_losses, probabilities = softmax_cross_entropy(logits, target, ignore_index=IGNORE_INDEX)
        parts["ohem"] = hardest_mean(pixel_losses, target, loss_config.ohem_fraction)
    else:
        logits = logits.float()  # once for all terms: a bf16 network's logits are cast (and their gradient) once
        if loss_config.ohem_weight > 0:
            parts["ohem"] = ohem_cross_entropy(logits, target, loss_config.ohem_fraction)
        probabilities = torch.softmax(logits, dim=1) if needs_probabilities else None
    if loss_config.ohem_weight > 0:
        total = total + loss_config.ohem_weight * parts["ohem"]
    if loss_config.lovasz_weight > 0:
        parts["lovasz"] = _lovasz_of_probabilities(probabilities, target)
        total = total + loss_config.lovasz_weight * parts["lovasz"]
    if loss_config.smooth_weight > 0:
        parts["smooth"] = _smoothness_of_probabilities(probabilities, guide)
        total = total + loss_config.smooth_weight * parts["smooth"]
    return total, {k: v.detach() for k, v in parts.items()}
