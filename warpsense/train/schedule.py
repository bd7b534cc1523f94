"""The epoch plan of a run (paper Alg. 1): how many epochs, which of them are warm-up, and the plan's fit to a
wall-time budget. The stages read it at each epoch (`Camera.on_epoch`), e.g. the CFA anneals its temperature."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass(frozen=True)
class Schedule:
    """Epochs of a run; the first ``warmup_epochs`` train the network on a frozen camera, the rest jointly.

    The run's config states the requested plan; a time budget (``train.time_budget_minutes``) may shorten it after
    the first epoch (`shortened`, with `epochs_within`). The config is never changed: the plan in use is this object,
    saved in each checkpoint so a resumed run keeps it.
    """

    epochs: int
    warmup_epochs: int

    @classmethod
    def from_config(cls, train_config) -> "Schedule":
        """The plan the [train] section requests."""
        return cls(train_config.epochs, train_config.warmup_epochs)

    def is_joint(self, epoch: int) -> bool:
        """Whether ``epoch`` (0-based) trains the camera too."""
        return epoch >= self.warmup_epochs

    def phase(self, epoch: int) -> str:
        """"warmup" or "joint", as recorded in metrics.jsonl."""
        return "joint" if self.is_joint(epoch) else "warmup"

    def epochs_within(self, budget_seconds: float, epoch_seconds: float) -> int:
        """How many epochs of ``epoch_seconds`` (plus a 10% margin for evaluation) fit ``budget_seconds``: at least
        2, at most the plan's."""
        return max(2, min(self.epochs, int(budget_seconds / (epoch_seconds * 1.1))))

    def shortened(self, epochs: int) -> "Schedule":
        """The plan cut to ``epochs``, warm-up shortened in proportion (kept at >= 1 epoch if it had any)."""
        if epochs >= self.epochs:
            return self
        if self.warmup_epochs >= self.epochs:  # a run without a joint phase keeps none
            warmup = epochs
        elif self.warmup_epochs:  # and one with both phases keeps both
            warmup = min(max(1, round(self.warmup_epochs * epochs / self.epochs)), epochs - 1)
        else:
            warmup = 0
        return dataclasses.replace(self, epochs=epochs, warmup_epochs=warmup)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)
