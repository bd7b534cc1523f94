"""Segmentation networks; `MODELS` is the registry (name -> constructor)."""

from __future__ import annotations

import inspect

from warpsense.models.dsunet import DSUNet

MODELS = {"dsunet": DSUNet}


def registered(name: str):
    """The constructor registered as ``name``; unknown names raise a KeyError listing the valid ones."""
    if name not in MODELS:
        raise KeyError(f"unknown model {name!r}; valid models: {', '.join(sorted(MODELS))}")
    return MODELS[name]


def build_model(name: str, **kwargs):
    """Construct a registered model (`registered`)."""
    return registered(name)(**kwargs)


def network_from_config(model_config, in_channels: int, num_classes: int, tile: int):
    """The network a config's ``[model]`` section describes, for ``in_channels`` inputs and ``num_classes`` outputs
    (``model.num_classes`` wins when set); the one place a config becomes a network, so every caller builds the same
    one.

    The network receives the ``[model]`` keys its constructor names (and ``in_channels``, ``num_classes``,
    ``tile``), no others: each network declares its own knobs by its signature, so none has to accept another
    network's keys only to refuse them."""
    values = {**vars(model_config), "in_channels": in_channels, "num_classes": model_config.num_classes or num_classes,
              "tile": tile}
    network = registered(model_config.name)
    accepted = inspect.signature(network).parameters
    return network(**{key: value for key, value in values.items() if key in accepted})


def count_parameters(model) -> int:
    return sum(p.numel() for p in model.parameters())


__all__ = ["DSUNet", "MODELS", "build_model", "count_parameters", "network_from_config"]
