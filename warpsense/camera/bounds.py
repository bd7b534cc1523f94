"""Learnable camera values held within physical bounds (f-number, exposure time, analog gain)."""

from __future__ import annotations

import math

import torch
from torch import nn


def log_bounded_parameter(value: float, low: float, high: float, learnable: bool = True) -> nn.Parameter:
    """The logit p that `log_bounded` maps to ``value`` in [``low``, ``high``] (a value at a bound: p = -inf or
    +inf, which only a fixed value should take)."""
    fraction = (math.log(value) - math.log(low)) / (math.log(high) - math.log(low))
    return nn.Parameter(torch.logit(torch.tensor(fraction, dtype=torch.float64)).float(), requires_grad=learnable)


def log_bounded(logit: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """low * (high / low) ** sigmoid(logit): a value in [low, high], uniform in its logarithm."""
    return low * (high / low) ** torch.sigmoid(logit)
