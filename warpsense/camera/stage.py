"""The protocol every camera stage follows, so that the camera, plots, predict and bench iterate stages instead of
naming them."""

from __future__ import annotations

from typing import Any, ClassVar

from torch import nn


class Stage(nn.Module):
    """A camera stage (SPEC section 3): an `nn.Module` that builds itself from its config section and reports its
    learned state.

    Subclasses set ``config_section`` (the name of their ``[section]`` in `configs/default.toml`, whose
    ``enabled`` key decides whether `Camera.from_config` constructs the stage) and implement `from_config`;
    stages with learnable state override `summary`.
    """

    config_section: ClassVar[str]

    @classmethod
    def from_config(cls, section) -> "Stage":
        """Build the stage from its config section (a dataclass of `warpsense.config`)."""
        raise NotImplementedError(f"{cls.__name__} does not implement from_config")

    def summary(self) -> dict[str, Any]:
        """The stage's learned state as JSON-ready values keyed by a name unique across stages (recorded in each
        epoch's metrics, read by `warpsense predict`); empty when it learns nothing."""
        return {}
