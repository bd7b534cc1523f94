"""Confusion-matrix segmentation metrics (accumulated on the device; no host sync per batch)."""

from __future__ import annotations

import torch

from warpsense.data.labels import IGNORE_INDEX


class ConfusionMatrix:
    """Confusion counts [K, K] (rows: label, columns: prediction); with ``per_image`` also each image's per-class
    (true positive, false positive, false negative) pixel counts [N, K, 3], which an image-level bootstrap
    resamples (`per_image_counts`)."""

    def __init__(self, num_classes: int, device, per_image: bool = False):
        self.num_classes = num_classes
        self.matrix = torch.zeros(num_classes, num_classes, dtype=torch.int64, device=device)
        self.images = 0
        self.per_image = per_image
        self._image_counts: list[torch.Tensor] = []

    def update(self, prediction: torch.Tensor, target: torch.Tensor) -> None:
        """prediction, target: [B, H, W] class indices; target == 255 is ignored."""
        valid = target != IGNORE_INDEX
        classes = self.num_classes
        if self.per_image:
            batch = prediction.shape[0]
            image = torch.arange(batch, device=target.device).view(-1, 1, 1).expand_as(target)
            index = (image * classes + target.long())[valid] * classes + prediction[valid]
            matrices = torch.bincount(index, minlength=batch * classes**2).view(batch, classes, classes)
            self.matrix += matrices.sum(0)
            true_positive = matrices.diagonal(dim1=1, dim2=2)
            self._image_counts.append(torch.stack([true_positive, matrices.sum(1) - true_positive,
                                                   matrices.sum(2) - true_positive], dim=-1))
        else:
            index = target[valid] * classes + prediction[valid]
            self.matrix += torch.bincount(index, minlength=classes**2).view(classes, classes)
        self.images += prediction.shape[0]

    def per_image_counts(self) -> torch.Tensor:
        """int64 [N, K, 3]: per image and class, (true positive, false positive, false negative) pixels."""
        if not self.per_image:
            raise RuntimeError("ConfusionMatrix: built without per_image")
        if not self._image_counts:
            return torch.zeros(0, self.num_classes, 3, dtype=torch.int64)
        return torch.cat(self._image_counts).cpu()

    def compute(self, class_names=None) -> dict:
        """mIoU over classes present in the labels or predictions, per-class IoU (None when absent), pixel accuracy,
        and the confusion counts ("confusion", [K][K] ints, rows: label, columns: prediction)."""
        counts = self.matrix.cpu()  # one copy to the host
        matrix = counts.double()
        true_positive = matrix.diag()
        union = matrix.sum(0) + matrix.sum(1) - true_positive
        iou = torch.where(union > 0, true_positive / union.clamp_min(1), torch.full_like(union, float("nan")))
        names = class_names or [str(i) for i in range(self.num_classes)]
        present = ~torch.isnan(iou)
        return {
            "miou": float(iou[present].mean()) if present.any() else 0.0,
            "per_class_iou": {name: (None if torch.isnan(v) else float(v)) for name, v in zip(names, iou)},
            "pixel_accuracy": float(true_positive.sum() / matrix.sum().clamp_min(1)),
            "num_images": self.images,
            "confusion": counts.tolist(),
        }
