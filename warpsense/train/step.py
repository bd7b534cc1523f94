"""One optimisation step of co-design training: forward (camera -> network) and loss, optionally compiled, backward,
camera-gradient throttling, learning-rate schedule and optimizer step, with the statistics kept on the device."""

from __future__ import annotations

import math

import torch

from warpsense.train.losses import segmentation_loss

COMPILE_MODES = ("off", "default", "reduce-overhead", "max-autotune")
LOSS_PARTS = ("ohem", "lovasz", "smooth")
STATISTICS = ("loss", *LOSS_PARTS, "steps", "nonfinite_steps")


def cosine_scale(step: int, total_steps: int) -> float:
    """Learning-rate multiplier of the cosine schedule: 1 at step 0, 0 at ``total_steps``."""
    return 0.5 * (1 + math.cos(math.pi * min(step, total_steps) / max(total_steps, 1)))


class TrainingStep:
    """Runs training steps and accumulates their statistics without a host synchronisation.

    Args:
        loss_config: the [loss] config section.
        optimizer: its param groups' initial ``lr`` are the base rates of the cosine schedule.
        camera_params: the learnable camera parameters (their gradient norm is clipped to ``camera_grad_clip``
            in the joint phase; 0 = no clip).
        total_steps: length of the cosine schedule.
        amp: bf16 autocast for the network.
        compile_mode: "off" or a `torch.compile` mode for the forward and loss (the backward is compiled with
            it); shapes are fixed by the training crop, so the step compiles once per phase.
    """

    def __init__(self, loss_config, optimizer: torch.optim.Optimizer, camera_params: list, total_steps: int,
                 amp: bool, camera_grad_clip: float = 0.0, compile_mode: str = "off"):
        if compile_mode not in COMPILE_MODES:
            raise ValueError(f"compile mode must be one of {COMPILE_MODES}, got {compile_mode!r}")
        self.loss_config = loss_config
        self.optimizer = optimizer
        self.camera_params = camera_params
        self.total_steps = total_steps
        self.amp = amp
        self.camera_grad_clip = camera_grad_clip
        self.base_lrs = [group["lr"] for group in optimizer.param_groups]
        self.forward_loss = self._forward_loss if compile_mode == "off" else \
            torch.compile(self._forward_loss, mode=None if compile_mode == "default" else compile_mode)
        self._sums: torch.Tensor | None = None  # float64 [len(STATISTICS)] on the device

    def _forward_loss(self, model, images, labels):
        logits, sensed = model(images, self.amp)
        loss, parts = segmentation_loss(logits, labels, sensed, self.loss_config)
        return loss, parts

    def __call__(self, model, images: torch.Tensor, labels: torch.Tensor, step: int, joint: bool) -> None:
        """One step at schedule position ``step``; ``joint``: camera gradients are applied (and clipped)."""
        loss, parts = self.forward_loss(model, images, labels)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if joint and self.camera_grad_clip > 0:
            trainable = [p for p in self.camera_params if p.grad is not None]
            if trainable:
                torch.nn.utils.clip_grad_norm_(trainable, self.camera_grad_clip)
        scale = cosine_scale(step, self.total_steps)
        for group, base_lr in zip(self.optimizer.param_groups, self.base_lrs):
            group["lr"] = base_lr * scale
        self.optimizer.step()
        self._accumulate(loss.detach(), parts)

    @property
    def totals(self) -> dict[str, torch.Tensor]:
        """Sums since the last `epoch_statistics`, by name (``STATISTICS``)."""
        return dict(zip(STATISTICS, self._sums)) if self._sums is not None else {}

    def _accumulate(self, loss: torch.Tensor, parts: dict) -> None:
        values = torch.stack([loss, *(parts.get(name, torch.zeros_like(loss)) for name in LOSS_PARTS)]).double()
        nonfinite = (~torch.isfinite(loss)).double()
        # a non-finite loss is counted, not summed: the epoch's mean stays readable
        step = torch.cat([torch.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0),
                          torch.ones_like(nonfinite).view(1), nonfinite.view(1)])
        self._sums = step if self._sums is None else self._sums + step

    def epoch_statistics(self, context) -> dict[str, float]:
        """Mean loss and parts over the steps since the last call (all ranks), and the count of non-finite losses;
        one host synchronisation."""
        if self._sums is None:
            return {}
        totals = dict(zip(STATISTICS, context.all_reduce_sum(self._sums).tolist()))
        self._sums = None
        steps = max(totals.pop("steps"), 1.0)
        nonfinite = int(totals.pop("nonfinite_steps"))
        finite_steps = max(steps - nonfinite, 1.0)
        statistics = {f"train_{name}" if name != "loss" else "train_loss": value / finite_steps
                      for name, value in totals.items()}
        statistics["nonfinite_steps"] = nonfinite
        return statistics
