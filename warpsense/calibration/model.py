"""The noise model a capture is fitted with: Poisson-Gaussian noise, clipped at the ADC's range and quantized.

A pixel of true signal y (white-level units after black-level subtraction, `warpsense.data.raw`) reads
z = clip(y + sqrt(a max(y, 0) + b) eps, lower, upper), eps ~ N(0, 1), rounded to a step of ``step``: ``a`` is the
shot-noise variance coefficient (the project's noise.shot), ``b`` the read-noise variance (noise.read squared).
Clipping is what a single capture cannot avoid: dark regions of a capture whose black level is at the ADC's zero
(`warpsense simulate`'s captures) lose their lower tail, and near-white regions their upper tail, so their mean is
raised (lowered) and their variance reduced; `clipped_moments` gives both, and a fit through them does not read
the reduced variance near the clip as less noise (Foi et al. 2008, section III).
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

_INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)


def noise_variance(y: np.ndarray, shot: float, read_variance: float) -> np.ndarray:
    """Variance a * max(y, 0) + b of the unclipped noise at signal ``y`` (white-level units)."""
    return shot * np.maximum(y, 0.0) + read_variance


EXACT_BELOW = 4.0
"""Noise deviations under this many quantization steps take the exact sum over the ADC's codes."""
_WINDOW = int(np.ceil(8 * EXACT_BELOW)) + 2
"""Codes either side of the nearest one that the exact sum takes: 8 deviations and more."""


def clipped_moments(y: np.ndarray, variance: np.ndarray, lower: np.ndarray | float, upper: np.ndarray | float,
                    step: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of the reading of signal ``y``: clip(N(y, variance), lower, upper), rounded to the ADC's
    codes lower + k step (k = 0 .. (upper - lower) / step; ``step`` 0: no rounding).

    Where the noise spans several steps, the continuous clipped moments (taken about y, for float64 precision where
    the variance is 1e-8 of y^2) with step^2 / 12 added for the unclipped part (Sheppard's correction, exact to
    within exp(-2 pi^2 variance / step^2) of it). Where the noise is under `EXACT_BELOW` steps (a read noise of a
    code or two at black), the sum over the codes themselves: there rounding and the clip at the zero code, which
    takes everything below half a step, move the moments by more than the fit's tolerance.

    Args:
        y: true signals, any shape.
        variance: unclipped noise variances (> 0), broadcast with ``y``.
        lower, upper: the clip bounds (white-level units; the ADC's zero code is -black / (white - black)).
        step: the quantization step (1 / (white - black) for a capture's integer codes; 0 for none).

    Returns:
        (mean, variance) of the reading, broadcast shape.
    """
    y, variance = np.broadcast_arrays(np.asarray(y, dtype=np.float64), np.asarray(variance, dtype=np.float64))
    sigma = np.sqrt(np.maximum(variance, 1e-30))
    low, high = lower - y, upper - y  # the bounds about y
    alpha, beta = low / sigma, high / sigma
    cdf_low, cdf_high = ndtr(alpha), ndtr(beta)
    pdf_low, pdf_high = np.exp(-0.5 * alpha**2) * _INV_SQRT_2PI, np.exp(-0.5 * beta**2) * _INV_SQRT_2PI
    inside = cdf_high - cdf_low
    first = low * cdf_low + high * (1 - cdf_high) + sigma * (pdf_low - pdf_high)
    second = (low**2 * cdf_low + high**2 * (1 - cdf_high) + sigma**2 * inside
              + sigma**2 * (alpha * pdf_low - beta * pdf_high))
    mean = y + first
    result = np.maximum(second - first**2, 0.0) + step**2 / 12.0 * inside
    if step > 0:
        exact = sigma < EXACT_BELOW * step
        if exact.any():
            mean, result = mean.copy(), result.copy()
            mean[exact], result[exact] = _code_moments(y[exact], sigma[exact], float(lower), float(upper), step)
    return mean, result


def _code_moments(y: np.ndarray, sigma: np.ndarray, lower: float, upper: float,
                  step: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of round-to-code(clip(N(y, sigma^2))) by summing over the codes within `_WINDOW` of y's:
    code k (value lower + k step) takes the readings within half a step of it, code 0 all below, the top code all
    above."""
    top = int(round((upper - lower) / step))
    nearest = np.round((y - lower) / step)
    codes = nearest[:, None] + np.arange(-_WINDOW, _WINDOW + 1)[None, :]
    valid = (codes >= 0) & (codes <= top)
    edge_low = np.where(codes <= 0, -np.inf, lower + (codes - 0.5) * step)
    edge_high = np.where(codes >= top, np.inf, lower + (codes + 0.5) * step)
    probability = (ndtr((edge_high - y[:, None]) / sigma[:, None]) - ndtr((edge_low - y[:, None]) / sigma[:, None]))
    probability = np.where(valid, probability, 0.0)
    offset = lower + codes * step - y[:, None]  # about y, for precision
    first = np.sum(probability * offset, axis=1)
    second = np.sum(probability * offset**2, axis=1)
    return y + first, np.maximum(second - first**2, 0.0)


def signal_from_mean(mean: np.ndarray, shot: float, read_variance: float, lower: np.ndarray | float,
                     upper: np.ndarray | float, step: float = 0.0, iterations: int = 30,
                     start: np.ndarray | None = None) -> np.ndarray:
    """The true signal y whose clipped mean (`clipped_moments`) is ``mean``, vectorised over bins.

    The clipped mean rises with y for any noise a capture can hold (its slope, the unclipped probability less the
    pull of the growing noise on the clipped tail, stays positive while the noise at the clip is under the range),
    and clipping moves it by less than 8 noise deviations of the range's top, so y lies in that bracket about the
    mean. Newton steps that leave the bracket, which shrinks with every step, are replaced by its midpoint; the
    iteration stops once every step is below 1e-12 of the range. ``start``: a first guess (default: the mean), e.g.
    the signals of a nearby curve.
    """
    mean = np.asarray(mean, dtype=np.float64)
    reach = 8.0 * np.sqrt(noise_variance(np.asarray(upper, dtype=np.float64), shot, read_variance))
    low, high = mean - reach, mean + reach
    y = mean.copy() if start is None else np.clip(np.asarray(start, dtype=np.float64), low, high)
    span = float(np.max(np.asarray(upper) - np.asarray(lower)))

    for _ in range(iterations):
        variance = noise_variance(y, shot, read_variance)
        sigma = np.sqrt(np.maximum(variance, 1e-30))
        value = clipped_moments(y, variance, lower, upper, step)[0]
        above = value > mean
        high = np.where(above, y, high)
        low = np.where(above, low, y)
        # d mean / dy = P(inside) + d sigma / dy * (pdf(alpha) - pdf(beta)): the tails' pull as the noise grows
        alpha, beta = (lower - y) / sigma, (upper - y) / sigma
        sigma_slope = np.where(y > 0, shot / (2 * sigma), 0.0)
        slope = (ndtr(beta) - ndtr(alpha)
                 + sigma_slope * (np.exp(-0.5 * alpha**2) - np.exp(-0.5 * beta**2)) * _INV_SQRT_2PI)
        with np.errstate(divide="ignore", invalid="ignore"):
            proposal = y - (value - mean) / slope
        inside = np.isfinite(proposal) & (proposal >= low) & (proposal <= high)
        new = np.where(inside, proposal, 0.5 * (low + high))
        if np.max(np.abs(new - y)) < 1e-12 * span:
            return new
        y = new
    return y
