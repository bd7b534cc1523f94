"""Level sets: a channel's samples (`warpsense.calibration.local`) grouped by level into (mean, variance, count)
points of its mean-variance curve.

Samples are ordered by their ring level and cut into sets of equal count. Which samples of a set count is decided
by statistics that share nothing with the centre's energy under Gaussian noise (a choice by the centre's energy
itself would bias it low):

- the ring's roughness: without a reference curve (the first pass), the smoothest `KEEP` fraction of each set (a
  set of smooth samples keeps a random part of them, a set with texture its flattest places); with a reference curve
  (the noise curve of the first pass's fit), every sample whose ring roughness is below the 95% point of what noise
  alone gives at its level (`SMOOTH`). A set of the second pass that keeps under `MIN_KEPT` of its samples is dropped
  (a level range of texture);
- the centre's own roughness (`local.OWN`: its other three detail filters, independent of its energy under Gaussian
  noise), below the 90% point of what noise gives (`OWN_SMOOTH`): texture sits in a few blocks (on CamVid frames a
  tenth of the samples a ring passes carries 80-90% of the texture they let through), and those blocks show it in
  all their detail filters, which their ring may not. Not at the lower clip, where a code or two of clipped noise
  ties the filters' energies together (a choice by the others there reads the variance 4% low).

The kept centres' block means give the set's level. The variance is read three ways:

- clear of the clips (noise of `GAUSSIAN_STEPS` codes or more, 4 deviations above the lower clip): the trimmed mean
  of the energies (`_trimmed`: those below the 99% point of the noise's distribution, a fixed point, over the cut's
  share), which a tail of texture does not move;
- near a clip: the mean, with only gross outliers cut (`TRUNCATE`: a hot pixel), since a code or two of noise clipped
  at zero has heavier tails than a Gaussian;
- at the lower clip (a black patch): the mean square of all eight zero-sum filters of the block (or the four
  detail filters, or the one), the most that do not see more than the one does: eight degrees of freedom a block
  where the read noise is read.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from warpsense.calibration.local import (
    DEGREES,
    OWN,
    RING,
    RING_DETAILS,
    STRIDE_CORRELATION,
    STRIDE_CORRELATION_ALL,
    STRIDE_CORRELATION_BLACK,
    PlaneSamples,
)

KEEP = 0.3
"""Fraction of each level set kept in the first pass, smoothest first by ring roughness."""
MIN_SET = 150
"""Least number of samples in a level set (before any is dropped)."""
MAX_SETS = 48
"""Most level sets per channel and capture."""
WIDTH = 0.3
"""A set's levels span at most this fraction of their distance to the nearer clip bound (`_partition`)."""
MIN_NARROW = 20
"""Least number of samples in a set that the span closes early."""
MIN_KEPT = 0.3
"""A level set of the second pass that keeps less than this fraction of its samples is dropped: its level range is
mostly texture, and the few samples whose ring looks smooth carry texture too."""

_CENTRE = chi2(DEGREES)
_RING = chi2(len(RING_DETAILS) * len(RING))
TRUNCATE = 30.0
"""Centre energies beyond TRUNCATE times the set's robust variance are dropped: a hot pixel, a dot the ring does
not see. Gaussian noise passes it but once in 2e7 samples; a tighter cut would bias a set near black, whose
readings (a code or two of noise, clipped at zero) have heavier tails than a Gaussian's."""
GAUSSIAN_STEPS = 3.0
"""A set whose noise spans this many ADC codes or more, 4 deviations clear of the lower clip, reads nearly Gaussian
noise: its variance is the trimmed mean of its energies (`_trimmed`)."""
AT_CLIP = 1.0
"""A set within AT_CLIP noise deviations of the lower clip (a black patch's) reads the eight or four filters."""
NEAR_CLIP_SIGMAS = 2.0
"""A set at the clip reads the eight (four) filters unless their mean energy exceeds the one filter's by more than
NEAR_CLIP_SIGMAS standard errors: texture, an edge or a gradient, which the others see more of."""
AGREE = 4.0
"""A sample counts only where its centre's mean is within AGREE standard deviations of its ring's."""
ROBUST = 0.98
ROBUST_FACTOR = float(chi2(DEGREES + 2).cdf(_CENTRE.ppf(ROBUST)) / ROBUST)
_ALL = len(RING_DETAILS)
ROBUST_FACTOR_ALL = float(chi2(_ALL + 2).cdf(chi2(_ALL).ppf(ROBUST)) / ROBUST)
ROBUST_FACTOR_BLACK = float(chi2(8 + 2).cdf(chi2(8).ppf(ROBUST)) / ROBUST)
"""E[e | e below its ROBUST quantile] / v under Gaussian noise (1, 4 and 8 degrees of freedom): `_robust` divides by
the first."""


def _robust(energy: np.ndarray) -> float:
    """A first estimate of the variance that a few outliers do not move: the mean of the energies below their 98%
    point, over that mean's share under Gaussian noise. (Not the median: a block of a code or two of noise clipped at
    zero reads mostly zeros, and the median of its energies is 0.)"""
    if energy.size == 0:
        return 0.0
    return float(np.mean(energy[energy <= np.quantile(energy, ROBUST)]) / ROBUST_FACTOR)


OWN_SMOOTH = float(chi2(len(OWN)).ppf(0.9) / len(OWN))
"""A sample of a set clear of the lower clip counts only where its own roughness (`local.OWN`) is below OWN_SMOOTH
times the noise variance (the reference curve's, else the set's first estimate): the 90% point of what noise alone
gives. On CamVid frames at shot 0.015 it takes the shot's bias from +5.4% to +4.1% (median of 8 frames)."""
TRIM = 0.99
"""A set of Gaussian noise reads the mean of its energies below TRIM's point of the noise's distribution, found as a
fixed point (`_trimmed`): texture adds energy to a minority of samples, and the cut takes its tail where the mean
alone would keep it. It costs a third of the estimate's efficiency (`TRIM_SPREAD`)."""


def _trim_constants(quantile: float, degrees: int) -> tuple[float, float, float]:
    """(the cut t, E[X | X < t], the estimator's variance times n) for X = chi2(degrees) / degrees and the fixed point
    v = mean(e | e < t v) / E[X | X < t] (an M-estimator: psi(e, v) = (e - f v) 1(e < t v))."""
    unit = chi2(degrees, scale=1.0 / degrees)
    cut = float(unit.ppf(quantile))
    upper = chi2(degrees + 2, scale=1.0 / degrees)  # E[X; X < t] = P(chi2(k + 2) < k t) for X = chi2(k) / k
    inside = float(upper.cdf(cut))
    factor = inside / quantile
    second = float(chi2(degrees + 4, scale=1.0 / degrees).cdf(cut)) * (degrees + 2) / degrees  # E[X^2; X < t]
    spread = second - 2 * factor * inside + factor**2 * quantile  # E[(X - f)^2; X < t]
    slope = factor * quantile - (cut - factor) * cut * float(unit.pdf(cut))
    return cut, factor, spread / slope**2


TRIM_CUT, TRIM_FACTOR, TRIM_SPREAD = _trim_constants(TRIM, DEGREES)
"""`_trimmed`'s cut and factor, and its variance over the plain mean's (2 / DEGREES) at n samples."""


def _trimmed(energy: np.ndarray, start: float) -> tuple[float, np.ndarray]:
    """The fixed point v = mean(e | e < TRIM_CUT v) / TRIM_FACTOR from ``start``, and the mask of the energies
    below the cut: consistent under Gaussian noise, and a tail of texture beyond the cut does not move it."""
    value = start
    for _ in range(50):
        below = energy < TRIM_CUT * value
        if below.sum() < 2:
            return value, below
        new = float(np.mean(energy[below])) / TRIM_FACTOR
        if abs(new - value) <= 1e-9 * value:
            return new, energy < TRIM_CUT * new
        value = new
    return value, energy < TRIM_CUT * value


SMOOTH_QUANTILE = 0.95
SMOOTH = float(_RING.ppf(SMOOTH_QUANTILE) / (len(RING_DETAILS) * len(RING)))
"""Ring roughness beyond SMOOTH times the reference variance marks a textured sample (the second pass): the 95%
point of the roughness noise alone gives, so that 5% of the smooth samples are lost and texture that adds a fifth
of the noise's variance is mostly caught."""


@dataclass
class LevelSets:
    """Points of one channel's mean-variance curve: level ``mean`` (white-level units), ``variance`` of the noise
    there, ``count`` of the samples behind each, and the variance of each point's mean (``mean_variance``) and of
    its variance (``variance_variance``) at the observed variance, for the fit's weights."""

    mean: np.ndarray
    variance: np.ndarray
    count: np.ndarray
    mean_variance: np.ndarray
    variance_variance: np.ndarray

    def __len__(self) -> int:
        return int(self.mean.size)

    @classmethod
    def empty(cls) -> "LevelSets":
        return cls(*(np.zeros(0) for _ in range(5)))


def _partition(order: np.ndarray, sorted_levels: np.ndarray, sorted_energy: np.ndarray, target: int,
               lower: float, upper: float) -> list[np.ndarray]:
    """Cut the samples (``order``, by level) into sets of ``target`` samples, a set closing early (at `MIN_NARROW`
    samples or more) where its levels would span more than `WIDTH` of its distance to the nearer clip bound or of 2
    noise deviations, whichever is more (the deviation from the median energy of the set's first samples): near a
    clip the reading's variance bends with the level, and a set mixing a black patch with a dark grey one would have
    a variance that is not the curve's at its mean level. Runs under `MIN_NARROW` samples are dropped."""
    sets, start = [], 0
    while start < order.size:
        first = sorted_levels[start]
        noise = np.sqrt(_robust(sorted_energy[start:start + MIN_NARROW]))
        distance = max(min(first - lower, upper - first), 2 * noise, 1e-12)
        end = min(start + target, order.size)
        wide = np.nonzero(sorted_levels[start:end] > first + WIDTH * distance)[0]
        if wide.size:
            end = start + int(wide[0])
        if end - start >= MIN_NARROW:
            sets.append(order[start:end])
        start = max(end, start + 1)
    return sets


def level_sets(samples: list[PlaneSamples], reference: Callable[[np.ndarray], np.ndarray] | None = None,
               min_set: int = MIN_SET, max_sets: int = MAX_SETS, lower: float = -np.inf, upper: float = np.inf,
               step: float = 0.0) -> tuple[LevelSets, np.ndarray]:
    """The level sets of one channel's samples (its site planes' together).

    Args:
        samples: the channel's site planes' samples.
        reference: the noise variance expected at a ring level (clipping included), from a first fit; None for
            the first pass (the smoothest `KEEP` of each set).
        lower, upper, step: the ADC's clip bounds and code step (white-level units), which decide the sets' widths
            near the clips and the cut.

    Returns:
        (the level sets, a boolean mask over the concatenated samples: those the sets kept).
    """
    def joined(name):
        return np.concatenate([getattr(s, name) for s in samples]) if samples else np.zeros(0)

    mean, energy, level, roughness, energy_all, own, energy_black = (
        joined(name) for name in ("mean", "energy", "level", "roughness", "energy_all", "own", "energy_black"))
    used = np.zeros(level.size, dtype=bool)
    sets = min(max_sets, level.size // min_set)
    if sets < 1:
        return LevelSets.empty(), used
    if reference is None:
        smooth_enough = None
    else:
        smooth_enough = roughness < SMOOTH * reference(level)
    order = np.argsort(level, kind="stable")
    points = {name: [] for name in ("mean", "variance", "count", "mean_variance", "variance_variance")}
    for members in _partition(order, level[order], energy[order], -(-level.size // sets), lower, upper):
        if smooth_enough is None:
            count = max(int(round(KEEP * members.size)), 2)
            smooth = members[np.argsort(roughness[members], kind="stable")[:count]]
        else:
            smooth = members[smooth_enough[members]]
            if smooth.size < MIN_KEPT * members.size:
                continue
        if smooth.size < 2:
            continue
        robust = _robust(energy[smooth])
        if not robust > 0:  # a set of identical values (all clipped): nothing to read
            continue
        # the centre's level must be the ring's, to within the noise of both means: a sample on an edge (a centre
        # in a dark patch, its ring half outside) would mix the readings of other levels into the set's, and near
        # a clip, where the variance bends with the level, the mixture's variance is not the curve's at its mean.
        # The centre's mean is independent of its detail energy, so this choice does not bias the energy either.
        agree = np.abs(mean[smooth] - level[smooth]) <= AGREE * np.sqrt(robust * (1 / 9 + 1 / (9 * len(RING))))
        smooth = smooth[agree]
        if smooth.size < 2:
            continue
        at_clip = np.mean(mean[smooth]) - lower <= AT_CLIP * np.sqrt(robust)
        if not at_clip:
            # the centre's own roughness, against the curve where there is one (else the set's first estimate)
            scale = reference(level[smooth]) if reference is not None else robust
            smooth = smooth[own[smooth] < OWN_SMOOTH * scale]
            if smooth.size < MIN_NARROW:
                continue
        gaussian = robust >= (GAUSSIAN_STEPS * step) ** 2 and np.mean(mean[smooth]) - lower > 4 * np.sqrt(robust)
        values, correlation = energy, STRIDE_CORRELATION
        if gaussian:
            variance, _ = _trimmed(energy[smooth], robust)
            kept, spread = smooth, TRIM_SPREAD * DEGREES / 2
        else:  # near a clip: only gross outliers cut; at the clip all eight (or the four) filters unless they see
            # more than the one: texture, an edge or a gradient
            one = float(np.mean(energy[smooth]))
            tolerance = one * (1 + NEAR_CLIP_SIGMAS * np.sqrt(2 * STRIDE_CORRELATION / smooth.size))
            for more, more_correlation, more_factor in ((energy_black, STRIDE_CORRELATION_BLACK, ROBUST_FACTOR_BLACK),
                                                        (energy_all, STRIDE_CORRELATION_ALL, ROBUST_FACTOR_ALL)):
                if at_clip and float(np.mean(more[smooth])) <= tolerance:
                    values, correlation = more, more_correlation
                    robust = _robust(values[smooth]) * ROBUST_FACTOR / more_factor
                    break
            kept = smooth[values[smooth] < TRUNCATE * robust]
            variance = float(np.mean(values[kept])) if kept.size else 0.0
            spread = 1.0
        if kept.size < MIN_NARROW:
            continue
        points["mean"].append(float(np.mean(mean[kept])))
        points["variance"].append(variance)
        points["count"].append(kept.size)
        # a block mean of 9 pixels; both point estimates are means over samples STRIDE apart
        points["mean_variance"].append(variance / 9.0 / kept.size)
        points["variance_variance"].append(2.0 * variance**2 * correlation * spread / kept.size)
        used[kept] = True
    return LevelSets(*(np.asarray(points[name], dtype=np.float64) for name in points)), used
