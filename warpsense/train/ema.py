"""An exponential moving average of a model's weights (Polyak averaging; as timm's ModelEmaV3), updated inside the
training step, so that it is captured with it in a CUDA graph."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


def averaged(ema: "WeightEMA | None"):
    """A context in which the model holds ``ema``'s averaged weights (`WeightEMA.applied`); a no-op without one."""
    return ema.applied() if ema is not None else contextlib.nullcontext()


class WeightEMA:
    """Averages every floating-point parameter and buffer of ``model`` (camera, network, BatchNorm statistics):
    after update n, shadow = d_n shadow + (1 - d_n) live with d_n = min(decay, (1 + n) / (10 + n)), so the early,
    random weights are forgotten fast.

    The tensors are the model's own (parameters and buffers keep their storage during training), the update is in
    place and its step count lives on the device: no host work, capturable. Build it after every module
    replacement (SyncBatchNorm) and before training.
    """

    def __init__(self, model: torch.nn.Module, decay: float):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"train.ema_decay must be in (0, 1) to average, got {decay}")
        self.decay = decay
        named = [(name, tensor) for name, tensor in model.state_dict(keep_vars=True).items()
                 if tensor.is_floating_point()]
        self.names = [name for name, _ in named]
        self.live = [tensor for _, tensor in named]
        self.shadow = [tensor.detach().clone() for tensor in self.live]
        self.updates = torch.zeros((), dtype=torch.float32, device=self.live[0].device)

    @torch.no_grad()
    def update(self) -> None:
        self.updates.add_(1.0)
        decay = torch.clamp((1.0 + self.updates) / (10.0 + self.updates), max=self.decay)
        deltas = torch._foreach_sub([tensor.detach() for tensor in self.live], self.shadow)
        torch._foreach_mul_(deltas, 1.0 - decay)
        torch._foreach_add_(self.shadow, deltas)

    @torch.no_grad()
    def _copy(self, sources: list[torch.Tensor]) -> None:
        for tensor, source in zip(self.live, sources):
            tensor.detach().copy_(source)

    @contextlib.contextmanager
    def applied(self) -> Iterator[None]:
        """Inside, the model holds the averaged weights (copied in place); on exit its own again."""
        saved = [tensor.detach().clone() for tensor in self.live]
        self._copy(self.shadow)
        try:
            yield
        finally:
            self._copy(saved)

    def apply_for_good(self) -> None:
        """Copy the averaged weights into the model for good (training is over)."""
        self._copy(self.shadow)

    def live_tensors(self) -> dict[str, torch.Tensor]:
        """The training weights and the update count, as checkpoint tensors (``live.<name>``, ``ema_updates``)."""
        # copies (on a CPU .cpu() would alias the model's own tensors, which `applied` overwrites)
        tensors = {f"live.{name}": tensor.detach().cpu().clone(memory_format=torch.contiguous_format)
                   for name, tensor in zip(self.names, self.live)}
        tensors["ema_updates"] = self.updates.detach().cpu().reshape(1)
        return tensors

    @torch.no_grad()
    def resume(self, tensors: dict[str, torch.Tensor]) -> None:
        """After `restore` put a checkpoint's averaged weights (``model.*``) into the model: take them as the
        average and put the training weights (``live.*``) back. A checkpoint without them (trained without EMA)
        starts the average at the model's weights."""
        self.shadow = [tensor.detach().clone() for tensor in self.live]
        if "ema_updates" not in tensors:
            return
        self._copy([tensors[f"live.{name}"] for name in self.names])
        self.updates.copy_(tensors["ema_updates"].reshape(()))
