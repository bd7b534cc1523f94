"""Level sets: a channel's samples (`warpsense.calibration.local`) grouped by level into (mean, variance, count)
points of its mean-variance curve.

Samples are ordered by their ring level and cut into sets of equal count. Which samples of a set count is decided
by their ring roughness alone (never by the centre's own energy, which would bias it), in one of two ways:

- without a reference curve (the first pass), the smoothest `KEEP` fraction of each set: a set of smooth samples
  keeps a random part of them (the roughness of a smooth sample is noise), a set with texture its flattest places;
- with a reference curve (the noise curve of the first pass's fit), every sample whose roughness is below the 99%
  point of the roughness that noise alone gives at its level: all but 1% of the smooth samples, and none of the
  textured ones whose texture rivals the noise.

A set of the second pass that keeps under `MIN_KEPT` of its samples is dropped (a level range of texture). The
kept centres' energies are averaged after dropping outliers about a robust first estimate (`_robust`): for
sets of nearly Gaussian noise (several codes, clear of the clip) those beyond its 99.9% point (`TIGHT`: a corner the
ring did not see), for the others only those far beyond anything the noise gives (`TRUNCATE`: a hot pixel), since
a code or two of noise clipped at zero has heavier tails than a Gaussian; the mean is divided by the cut's factor.
The kept centres' block means give the set's level.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from warpsense.calibration.local import (
    DEGREES,
    RING,
    RING_DETAILS,
    STRIDE_CORRELATION,
    STRIDE_CORRELATION_ALL,
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
TRUNCATED_FACTOR = float(chi2(DEGREES + 2).cdf(TRUNCATE * DEGREES) / _CENTRE.cdf(TRUNCATE * DEGREES))
"""E[e | e < TRUNCATE v] / v under Gaussian noise."""
GAUSSIAN_STEPS = 3.0
"""A set whose noise spans this many ADC codes or more, 4 deviations clear of the lower clip, reads nearly Gaussian
noise, and its energies are cut at `TIGHT` instead of `TRUNCATE`."""
TIGHT = float(_CENTRE.ppf(0.999) / DEGREES)
"""The 99.9% point of the energy under Gaussian noise (over its variance): a corner the ring does not see."""
TIGHT_FACTOR = float(chi2(DEGREES + 2).cdf(TIGHT * DEGREES) / _CENTRE.cdf(TIGHT * DEGREES))
"""E[e | e < TIGHT v] / v under Gaussian noise (E[X; X < t] = k P(chi2(k + 2) < t) for X ~ chi2(k))."""
NEAR_CLIP_ALL, NEAR_CLIP_SIGMAS = True, 2.0
AT_CLIP = 1.0
"""Only a set within AT_CLIP noise deviations of the lower clip (a black patch's) reads all four filters."""
"""A set near a clip reads all four detail filters unless their mean energy exceeds the one filter's by more than
NEAR_CLIP_SIGMAS standard errors: texture, which the other three filters see 2-3x more of (CamVid frames)."""
AGREE = 4.0
"""A sample counts only where its centre's mean is within AGREE standard deviations of its ring's."""
ROBUST = 0.98
ROBUST_FACTOR = float(chi2(DEGREES + 2).cdf(_CENTRE.ppf(ROBUST)) / ROBUST)
_ALL = len(RING_DETAILS)
ROBUST_FACTOR_ALL = float(chi2(_ALL + 2).cdf(chi2(_ALL).ppf(ROBUST)) / ROBUST)
"""E[e | e below its ROBUST quantile] / v under Gaussian noise: `_robust` divides by it."""


def _robust(energy: np.ndarray) -> float:
    """A first estimate of the variance that a few outliers do not move: the mean of the energies below their 98%
    point, over that mean's share under Gaussian noise. (Not the median: a block of a code or two of noise clipped at
    zero reads mostly zeros, and the median of its energies is 0.)"""
    if energy.size == 0:
        return 0.0
    return float(np.mean(energy[energy <= np.quantile(energy, ROBUST)]) / ROBUST_FACTOR)
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

    mean, energy, level, roughness, energy_all = (joined(name) for name in ("mean", "energy", "level", "roughness",
                                                                            "energy_all"))
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
        gaussian = robust >= (GAUSSIAN_STEPS * step) ** 2 and np.mean(mean[smooth]) - lower > 4 * np.sqrt(robust)
        if gaussian:
            values, correlation, limit, factor = energy, STRIDE_CORRELATION, TIGHT, TIGHT_FACTOR
        else:  # near a clip: only gross outliers cut, and all four filters unless they see texture
            values, correlation, limit, factor = energy, STRIDE_CORRELATION, TRUNCATE, 1.0
            one, four = float(np.mean(energy[smooth])), float(np.mean(energy_all[smooth]))
            at_clip = np.mean(mean[smooth]) - lower <= AT_CLIP * np.sqrt(robust)
            if NEAR_CLIP_ALL and at_clip and four <= one * (1 + NEAR_CLIP_SIGMAS * np.sqrt(2 * STRIDE_CORRELATION
                                                                                          / smooth.size)):
                values, correlation = energy_all, STRIDE_CORRELATION_ALL
                robust = _robust(values[smooth]) * ROBUST_FACTOR / ROBUST_FACTOR_ALL
        kept = smooth[values[smooth] < limit * robust]
        if kept.size < 2:
            continue
        variance = float(np.mean(values[kept]) / factor)
        points["mean"].append(float(np.mean(mean[kept])))
        points["variance"].append(variance)
        points["count"].append(kept.size)
        # a block mean of 9 pixels; both point estimates are means over samples STRIDE apart
        points["mean_variance"].append(variance / 9.0 / kept.size)
        points["variance_variance"].append(2.0 * variance**2 * correlation / kept.size)
        used[kept] = True
    return LevelSets(*(np.asarray(points[name], dtype=np.float64) for name in points)), used
