"""Confusion-matrix segmentation metrics (accumulated on the device; no host sync per batch)."""

from __future__ import annotations

import torch

from warpsense.data.labels import IGNORE_INDEX


class ConfusionMatrix:
    def __init__(self, num_classes: int, device):
        self.num_classes = num_classes
        self.matrix = torch.zeros(num_classes, num_classes, dtype=torch.int64, device=device)
        self.images = 0

    def update(self, prediction: torch.Tensor, target: torch.Tensor) -> None:
        """prediction, target: [B, H, W] class indices; target == 255 is ignored."""
        valid = target != IGNORE_INDEX
        index = target[valid] * self.num_classes + prediction[valid]
        self.matrix += torch.bincount(index, minlength=self.num_classes**2).view(self.num_classes, self.num_classes)
        self.images += prediction.shape[0]

    def compute(self, class_names=None) -> dict:
        """mIoU over classes present in the labels or predictions, per-class IoU (NaN when absent), pixel accuracy."""
        matrix = self.matrix.double().cpu()
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
        }
