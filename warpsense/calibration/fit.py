"""The fit of the noise curve variance = a y + b to level sets, clipping and quantization included.

Each level set i gives a level m_i (a mean of clipped readings) and a variance v_i, both nearly Gaussian about
their expectations under the model (means of hundreds of samples). For a curve (a, b) the set's true signal y_i is
the one whose clipped mean is m_i (`warpsense.calibration.model.signal_from_mean`: m_i is a mean of ~9 n_i pixels,
so it pins y_i far more tightly than v_i pins the curve), and v_i is compared with the reading's variance at y_i
(`clipped_moments`), with the standard error of v_i at the model's variance (2 V^2 c / n_i, plus the curve's slope
squared times m_i's variance). This profiles out the true signals of Foi et al. 2008 (eq. 31-32) instead of
integrating over them; with level sets of hundreds of samples the two agree to well under the intervals.

The fit is iteratively reweighted least squares over (log a, b >= 0): it starts from a line through the sets clear
of the clips (`_initial`), each round fixes the standard errors at the last round's curve (the model's variance,
not the noisy observed one, which would pull the curve down) and solves for the curve, with a loss that grows
linearly beyond one standard error (`LOSS`); the rounds stop when the curve moves by less than 1e-6 of itself, or
when a round would make the fit worse at its own standard errors (`_cost`: from a start far from the curve, the
errors of one round can send the next to a curve that explains nothing). The 95% intervals come from the last
round's Jacobian: Wald intervals for log a and for b (b's lower end clipped at 0, then both ends square-rooted for
the read noise), widened by the overdispersion, the fit's chi-square per degree of freedom where above 1 (texture
the smooth-sample choice let through, fixed-pattern noise, a model that is not the capture's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize

from warpsense.calibration.levels import LevelSets
from warpsense.calibration.model import clipped_moments, noise_variance, signal_from_mean

Z95 = 1.959963984540054
"""The standard normal's 97.5% point."""
ROUNDS = 12
"""Most reweighting rounds."""
LOSS, LOSS_SCALE = "soft_l1", 1.0
"""The solver's loss on the weighted residuals: quadratic within LOSS_SCALE standard errors, linear beyond, so that a
level set that texture inflated (a positive outlier of several errors) pulls the curve by its sign, not its size."""


@dataclass
class Group:
    """Level sets that share one ADC: their clip bounds and quantization step (white-level units)."""

    sets: LevelSets
    lower: float
    upper: float
    step: float


@dataclass
class NoiseFit:
    """A fitted noise curve: ``shot`` (variance coefficient a) and ``read`` (standard deviation, sqrt b), in units
    of the white level, with their 95% intervals, the points' count, and the overdispersion (chi-square per degree
    of freedom of the fit, 1 for a fit as good as the noise allows)."""

    shot: float
    read: float
    shot_interval: tuple[float, float]
    read_interval: tuple[float, float]
    points: int
    overdispersion: float
    covariance: np.ndarray  # of (log shot, read variance), overdispersion included

    def to_dict(self) -> dict:
        return {"shot": self.shot, "read": self.read, "shot_interval": list(self.shot_interval),
                "read_interval": list(self.read_interval), "points": self.points,
                "overdispersion": self.overdispersion}

    def variance(self, y: np.ndarray, lower: float, upper: float, step: float) -> np.ndarray:
        """The reading's variance at signal ``y`` under this curve (clipping and quantization included)."""
        return clipped_moments(y, noise_variance(y, self.shot, self.read**2), lower, upper, step)[1]


class FitError(ValueError):
    """Too few level sets to fit a curve."""


class _Curve:
    """The model's variances at the sets' levels for trial curves, the sets' true signals profiled out: each trial
    inverts the clipped mean (`signal_from_mean`) from the last trial's signals, which are close to its own, so a
    few Newton steps suffice; sets far from the clips (6 deviations) take their mean as the signal."""

    def __init__(self, groups: list[Group]):
        self.groups = groups
        self.signals = [group.sets.mean.copy() for group in groups]

    def signal(self, index: int, shot: float, read_variance: float) -> np.ndarray:
        group, signal = self.groups[index], self.signals[index].copy()
        sets = group.sets
        spread = 6.0 * np.sqrt(np.maximum(sets.variance, noise_variance(sets.mean, shot, read_variance)))
        near = (sets.mean - group.lower < spread) | (group.upper - sets.mean < spread)
        if near.any():
            signal[near] = signal_from_mean(sets.mean[near], shot, read_variance, group.lower, group.upper,
                                            group.step, start=signal[near])
        self.signals[index] = signal
        return signal

    def variances(self, index: int, shot: float, read_variance: float) -> np.ndarray:
        group = self.groups[index]
        signal = self.signal(index, shot, read_variance)
        return clipped_moments(signal, noise_variance(signal, shot, read_variance), group.lower, group.upper,
                               group.step)[1]

    def weights(self, shot: float, read_variance: float) -> list[np.ndarray]:
        """1 / the sets' standard errors under the curve (a, b): 2 V^2 c / n at the model's variance V, plus the
        curve's slope in the observed mean squared times the mean's variance."""
        weights = []
        for index, group in enumerate(self.groups):
            sets = group.sets
            signal = self.signal(index, shot, read_variance)
            variance = clipped_moments(signal, noise_variance(signal, shot, read_variance), group.lower,
                                       group.upper, group.step)[1]
            delta = 1e-7 + 1e-4 * np.abs(signal)
            mean_hi, var_hi = clipped_moments(signal + delta, noise_variance(signal + delta, shot, read_variance),
                                              group.lower, group.upper, group.step)
            mean_lo, var_lo = clipped_moments(signal - delta, noise_variance(signal - delta, shot, read_variance),
                                              group.lower, group.upper, group.step)
            slope = (var_hi - var_lo) / np.maximum(mean_hi - mean_lo, 1e-30)
            ratio = variance / np.maximum(sets.variance, 1e-30)  # the sets' error variances at the model's variance
            error = sets.variance_variance * ratio**2 + slope**2 * sets.mean_variance * ratio
            weights.append(1.0 / np.sqrt(np.maximum(error, 1e-300)))
        return weights

    def residuals(self, theta: np.ndarray, weights: list[np.ndarray]) -> np.ndarray:
        shot, read_variance = float(np.exp(theta[0])), float(theta[1])
        return np.concatenate([(group.sets.variance - self.variances(index, shot, read_variance)) * weights[index]
                               for index, group in enumerate(self.groups)])


def _initial(groups: list[Group]) -> np.ndarray:
    """The first round's curve (log a, b): a weighted least-squares line through the sets clear of the clips (4
    noise deviations from either bound, where clipping moves neither moment; every set where fewer than 3 are clear),
    each weighted by sqrt(count) over the line's variance there (a set's standard error grows as its variance).
    Weights from each set's own variance, or sets near a clip (whose variance the clip reduces) in the line, started
    the fit at a quarter of the shot coefficient on a capture of the tests' scene at 14 bits, where it stayed."""
    means = np.concatenate([g.sets.mean for g in groups])
    variances = np.concatenate([g.sets.variance for g in groups])
    counts = np.concatenate([g.sets.count for g in groups])
    lower = np.concatenate([np.full(len(g.sets), g.lower) for g in groups])
    upper = np.concatenate([np.full(len(g.sets), g.upper) for g in groups])
    deviation = np.sqrt(np.maximum(variances, 0.0))
    clear = (means - lower > 4 * deviation) & (upper - means > 4 * deviation) & (variances > 0)
    if clear.sum() < 3:
        clear = variances > 0
    means, variances, counts = np.maximum(means[clear], 0), variances[clear], counts[clear]
    # the errors from the line, not from each set's own variance (which would favour the sets drawn low): first a
    # line of pure shot noise (variance proportional to the level), then twice the last line's
    line = np.maximum(means, 1e-12)
    shot = read_variance = 0.0
    for _ in range(3):
        weights = np.sqrt(counts) / line
        design = np.stack([means, np.ones_like(means)], axis=1) * weights[:, None]
        (shot, read_variance), *_ = np.linalg.lstsq(design, variances * weights, rcond=None)
        fitted = shot * means + read_variance
        if not np.all(fitted > 0):
            break
        line = fitted
    if not shot > 0:
        shot = max(float(np.median(variances / np.maximum(means, 1e-6))), 1e-12)
    return np.array([np.log(shot), max(float(read_variance), 0.0)])


def _cost(curve: "_Curve", theta: np.ndarray) -> float:
    """The fit's objective at ``theta`` with the standard errors at ``theta`` itself: how the rounds' curves are
    compared (each round's own cost is at the last round's errors)."""
    weights = curve.weights(float(np.exp(theta[0])), float(theta[1]))
    residuals = curve.residuals(theta, weights)
    return float(np.sum(2.0 * (np.sqrt(1.0 + (residuals / LOSS_SCALE) ** 2) - 1.0)))


def fit_noise(groups: list[Group]) -> NoiseFit:
    """Fit (shot, read) to the level sets of ``groups`` (see the module docstring).

    Raises:
        FitError: fewer than 3 level sets.
    """
    groups = [group for group in groups if len(group.sets)]
    points = sum(len(group.sets) for group in groups)
    if points < 3:
        raise FitError(f"{points} level set(s), at least 3 needed")
    theta = _initial(groups)
    scale = max(float(np.max(np.concatenate([g.sets.variance for g in groups]))), 1e-30)
    curve = _Curve(groups)
    cost = _cost(curve, theta)
    for _ in range(ROUNDS):
        weights = curve.weights(float(np.exp(theta[0])), float(theta[1]))
        solution = optimize.least_squares(curve.residuals, theta, args=(weights,), method="trf", loss=LOSS,
                                          f_scale=LOSS_SCALE,
                                          bounds=([-np.inf, 0.0], [np.inf, np.inf]), x_scale=[1.0, scale],
                                          xtol=1e-10, ftol=1e-12, gtol=1e-12)
        new_cost = _cost(curve, solution.x)
        if not new_cost <= cost * (1 + 1e-9) + 1e-12:  # a round that makes the fit worse at its own errors
            break
        moved = abs(solution.x[0] - theta[0]) + abs(solution.x[1] - theta[1]) / scale
        theta, cost = solution.x, new_cost
        if moved < 1e-6:
            break
    weights = curve.weights(float(np.exp(theta[0])), float(theta[1]))
    residuals = curve.residuals(theta, weights)
    overdispersion = max(1.0, float(np.sum(residuals**2)) / max(points - 2, 1))
    jacobian = _jacobian(curve, theta, weights, scale)
    covariance = np.linalg.pinv(jacobian.T @ jacobian) * overdispersion
    shot, read_variance = float(np.exp(theta[0])), float(theta[1])
    shot_error = float(np.sqrt(max(covariance[0, 0], 0.0)))
    variance_error = float(np.sqrt(max(covariance[1, 1], 0.0)))
    shot_interval = (shot * float(np.exp(-Z95 * shot_error)), shot * float(np.exp(Z95 * shot_error)))
    read_interval = (float(np.sqrt(max(read_variance - Z95 * variance_error, 0.0))),
                     float(np.sqrt(read_variance + Z95 * variance_error)))
    return NoiseFit(shot, float(np.sqrt(read_variance)), shot_interval, read_interval, points,
                    float(overdispersion), covariance)


def _jacobian(curve: _Curve, theta: np.ndarray, weights: list[np.ndarray], scale: float) -> np.ndarray:
    """d(weighted residuals)/d(log a, b) by central differences (b's step relative to the sets' variances; at
    b = 0 a one-sided one)."""
    columns = []
    for index, step in ((0, 1e-5), (1, 1e-6 * scale)):
        shift = np.zeros(2)
        shift[index] = step
        low, high = theta - shift, theta + shift
        low[1] = max(low[1], 0.0)
        columns.append((curve.residuals(high, weights) - curve.residuals(low, weights)) / (high - low)[index])
    return np.stack(columns, axis=1)
