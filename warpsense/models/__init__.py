"""Segmentation networks; `MODELS` is the registry (name -> constructor)."""

from __future__ import annotations

from warpsense.models.dsunet import DSUNet
from warpsense.models.packunet import PackUNet

MODELS = {"dsunet": DSUNet, "packunet": PackUNet}


def build_model(name: str, **kwargs):
    """Construct a registered model; unknown names raise a KeyError listing the valid ones."""
    if name not in MODELS:
        raise KeyError(f"unknown model {name!r}; valid models: {', '.join(sorted(MODELS))}")
    return MODELS[name](**kwargs)


def count_parameters(model) -> int:
    return sum(p.numel() for p in model.parameters())


__all__ = ["DSUNet", "PackUNet", "MODELS", "build_model", "count_parameters"]
