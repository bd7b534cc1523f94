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


def network_from_config(model_config, in_channels: int, num_classes: int, tile: int):
    """The network a config's ``[model]`` section describes (every key that shapes it), for ``in_channels`` inputs
    and ``num_classes`` outputs (``model.num_classes`` wins when set); the one place a config becomes a network, so
    every caller builds the same one."""
    return build_model(model_config.name, in_channels=in_channels,
                       num_classes=model_config.num_classes or num_classes, width=model_config.width, tile=tile,
                       channels_last=model_config.channels_last, context=model_config.context,
                       squeeze=model_config.squeeze, input_transform=model_config.input_transform,
                       anscombe_offset=model_config.anscombe_offset, full_width=model_config.full_width,
                       full_depth=model_config.full_depth, decoder_join=model_config.decoder_join)


def count_parameters(model) -> int:
    return sum(p.numel() for p in model.parameters())


__all__ = ["DSUNet", "PackUNet", "MODELS", "build_model", "count_parameters", "network_from_config"]
