"""Learnable camera values held within physical bounds (f-number, exposure time, analog gain).

A value v in [low, high] is stored as a logit p with v = low * (high / low) ** sigmoid(p) (log-uniform). A bound
itself has no finite logit (p = -inf or +inf), and an infinite parameter is non-finite from the first optimizer
step on, so a start on a bound is stored finitely:

- a learnable value on its bound (or nearer to it than `BOUND_MARGIN` of the log range) starts that margin inside
  (f/1.4 in [1.4, 8] starts at f/1.4024 and f/8 at f/7.986, 1 ms in [1, 30] at 1.0034 ms and 30 ms at 29.90 ms, a
  gain of 1 in [1, 64] at 1.0042 and 64 at 63.73), where its gradient is finite and non-zero, so it can move off
  the bound;
- a fixed value takes the logit +-`FIXED_LOGIT`, whose sigmoid rounds to exactly 0 or 1 in float32 and float64, so
  it is the bound itself.
"""

from __future__ import annotations

import math

import torch
from torch import nn

BOUND_MARGIN = 1e-3
"""Share of the log range between a learnable value's bound and the start it takes there."""
FIXED_LOGIT = 50.0
"""|logit| of a fixed value on its bound: exp(-50) ~ 2e-22 vanishes next to 1 in float64 (and float32)."""


def check_log_bounds(key: str, value: float, low: float, high: float,
                     bound_keys: tuple[str, str] = ("low", "high")) -> str | None:
    """Why ``value`` cannot start ``key`` within [``low``, ``high``] (a message naming the keys), or None.

    Args:
        key: the config key of the start (e.g. "optics.f_number").
        value: the start.
        low, high: the bounds, which must satisfy 0 < low < high.
        bound_keys: the names of the bounds in the message (e.g. ("optics.f_number_min", "optics.f_number_max")).
    """
    names = f"[{bound_keys[0]}, {bound_keys[1]}] = [{low}, {high}]"
    if not (math.isfinite(low) and math.isfinite(high) and 0 < low < high):
        return f"{key} is learned within {names}: the bounds must satisfy 0 < low < high"
    if not (math.isfinite(value) and low <= value <= high):
        return f"{key} = {value} must lie within {names}"
    return None


def log_bounded_parameter(value: float, low: float, high: float, learnable: bool = True, key: str = "value",
                          bound_keys: tuple[str, str] = ("low", "high")) -> nn.Parameter:
    """The finite logit p that `log_bounded` maps to ``value`` in [``low``, ``high``] (see the module docstring for
    a value on a bound).

    Args:
        value: the start, within [low, high].
        low, high: the bounds, 0 < low < high.
        learnable: whether p takes gradients; a learnable start on a bound (or nearer to it than `BOUND_MARGIN`)
            moves to `BOUND_MARGIN` inside it.
        key, bound_keys: the config keys of the start and of its bounds, named in the error.

    Raises:
        ValueError: bounds or start outside what is stated above, naming ``key``.
    """
    problem = check_log_bounds(key, value, low, high, bound_keys)
    if problem:
        raise ValueError(problem)
    fraction = (math.log(value) - math.log(low)) / (math.log(high) - math.log(low))
    if learnable:
        fraction = min(max(fraction, BOUND_MARGIN), 1 - BOUND_MARGIN)
    logit = torch.logit(torch.tensor(fraction, dtype=torch.float64)).clamp(-FIXED_LOGIT, FIXED_LOGIT)
    return nn.Parameter(logit.float(), requires_grad=learnable)


def log_bounded(logit: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """low * (high / low) ** sigmoid(logit): a value in [low, high], uniform in its logarithm."""
    return low * (high / low) ** torch.sigmoid(logit)
