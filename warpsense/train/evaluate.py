"""Evaluation of a model on a dataset: mIoU / per-class IoU / pixel accuracy, and the robustness sweep (mIoU as one
camera factor moves off the operating point). `warpsense eval` scores a checkpoint with them: `warpsense.evaluation`."""

from __future__ import annotations

import torch
from torch.nn import functional as F
from torch.utils.data import DataLoader, Subset
from tqdm import tqdm

from warpsense.train.metrics import ConfusionMatrix


@torch.no_grad()
def evaluate(model, dataset, device, batch_size: int = 4, context=None, class_names=None, amp: bool = False,
             progress: bool = False, blur_sigma: float = 0.0, flip: bool = False, per_image: bool = False) -> dict:
    """Metrics of ``model`` on ``dataset`` (full images, eval-mode camera: noise seeded by each image's index).

    With a distributed ``context`` each rank takes every world_size-th image and the confusion matrices are summed.
    ``blur_sigma`` > 0 adds a Gaussian blur (pixels) to the radiance before the camera (robustness sweep).
    ``flip``: test-time augmentation on each capture, the CFA phase kept (`SensingModel.probabilities`).
    ``per_image``: also return "image_counts", int64 [N, K, 3] per-image (TP, FP, FN) pixels per class (not with
    a distributed context).
    """
    if per_image and context is not None and context.enabled:
        raise ValueError("evaluate: per_image counts are gathered on one process (no distributed context)")
    was_training = model.training
    model.eval()
    indices = list(range(len(dataset)))
    if context is not None and context.enabled:
        indices = indices[context.rank :: context.world_size]
        dataset = Subset(dataset, indices)
    indices = torch.tensor(indices, dtype=torch.int64)
    loader = DataLoader(dataset, batch_size=batch_size, shuffle=False)
    num_classes = model.network.head.out_channels
    confusion = ConfusionMatrix(num_classes, device, per_image)
    for batch, (images, labels) in enumerate(tqdm(loader, desc="eval", disable=not progress, leave=False)):
        images, labels = images.to(device), labels.to(device)
        if blur_sigma > 0:
            images = gaussian_blur(model.radiance(images), blur_sigma)
        image_index = indices[batch * batch_size : batch * batch_size + images.shape[0]]
        confusion.update(model.probabilities(images, amp, image_index, flip).argmax(dim=1), labels)
    if context is not None and context.enabled:
        context.all_reduce_sum(confusion.matrix)
        images_seen = torch.tensor([confusion.images], device=device)
        confusion.images = int(context.all_reduce_sum(images_seen))
    model.train(was_training)
    metrics = confusion.compute(class_names)
    if per_image:
        metrics["image_counts"] = confusion.per_image_counts()
    return metrics


def robustness_sweep(model, dataset, device, batch_size: int, class_names, amp: bool,
                     progress: bool = True) -> list[dict]:
    """mIoU under extra blur, scaled noise and other bit depths, one factor at a time, the others at the
    checkpoint's operating point; the camera is restored afterwards.

    Args:
        model: a `SensingModel`; its camera's what-if values (`Camera.what_if_values`) are the operating point, and
            only the factors it has are swept (no noise: no noise scales).
        dataset, device, batch_size, class_names, amp: as `evaluate` takes them.
        progress: a progress bar over the settings.

    Returns:
        One row per setting: {"factor", "value", "miou", "operating_point"}, the last true where the value is the
        checkpoint's own.
    """
    camera = model.camera
    operating = {"blur_sigma_px": 0.0, **camera.what_if_values()}
    settings = [("blur_sigma_px", sigma) for sigma in (0.0, 0.5, 1.0, 2.0)]
    if "noise_scale" in operating:
        settings += [("noise_scale", scale) for scale in (0.5, 1.0, 2.0, 4.0)]
    if "bits" in operating:
        settings += [("bits", value) for value in (4, 6, 8, 10, 12)]
    rows = []
    bar = tqdm(settings, desc="sweep", disable=not progress)
    for factor, value in bar:
        bar.set_postfix_str(f"{factor}={value}")
        # blur is no camera override: `evaluate` blurs the radiance before the camera
        what_if = {} if factor == "blur_sigma_px" else {factor: value}
        with camera.overridden(**what_if):
            metrics = evaluate(model, dataset, device, batch_size, class_names=class_names, amp=amp,
                               blur_sigma=value if factor == "blur_sigma_px" else 0.0)
        rows.append({"factor": factor, "value": value, "miou": metrics["miou"],
                     "operating_point": value == operating[factor]})
    return rows


def gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """``image`` [B, C, H, W] blurred by a separable Gaussian of ``sigma`` pixels (3 sigma wide), edges replicated."""
    radius = max(1, int(3 * sigma + 0.5))
    x = torch.arange(-radius, radius + 1, dtype=image.dtype, device=image.device)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = kernel / kernel.sum()
    channels = image.shape[1]
    image = F.pad(image, (radius, radius, radius, radius), mode="replicate")
    image = F.conv2d(image, kernel.view(1, 1, 1, -1).expand(channels, 1, 1, -1), groups=channels)
    return F.conv2d(image, kernel.view(1, 1, -1, 1).expand(channels, 1, -1, 1), groups=channels)
