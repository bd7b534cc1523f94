"""Level sets: a channel's samples (`warpsense.calibration.local`) grouped by level into (mean, variance, count)
points of its mean-variance curve.

Samples are ordered by their ring level and cut into sets of equal count. Which samples of a set count is decided
by their ring roughness alone (never by the centre's own energy, which would bias it), in one of two ways:

- without a reference curve (the first pass), the smoothest `KEEP` fraction of each set: a set of smooth samples
  keeps a random part of them (the roughness of a smooth sample is noise), a set with texture its flattest places;
- with a reference curve (the noise curve of the first pass's fit), every sample whose roughness is below the 99%
  point of the roughness that noise alone gives at its level: all but 1% of the smooth samples, and none of the
  textured ones whose texture rivals the noise.

The kept centres' energies are averaged after dropping the outliers far beyond anything the noise gives (`TRUNCATE`
times a robust first estimate, the set's median: a hot pixel, a dot the ring does not see); the kept centres'
block means give the set's level.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from warpsense.calibration.local import DEGREES, RING, RING_DETAILS, STRIDE_CORRELATION, PlaneSamples

KEEP = 0.3
"""Fraction of each level set kept in the first pass, smoothest first by ring roughness."""
MIN_SET = 150
"""Least number of samples in a level set (before any is dropped)."""
MAX_SETS = 48
"""Most level sets per channel and capture."""

_CENTRE = chi2(DEGREES)
_RING = chi2(len(RING_DETAILS) * len(RING))
TRUNCATE = 30.0
"""Centre energies beyond TRUNCATE times the set's robust variance are dropped: a hot pixel, a dot the ring does
not see. Gaussian noise passes it but once in 2e7 samples; a tighter cut would bias a set near black, whose
readings (a code or two of noise, clipped at zero) have heavier tails than a Gaussian's."""
TRUNCATED_FACTOR = float(chi2(DEGREES + 2).cdf(TRUNCATE * DEGREES) / _CENTRE.cdf(TRUNCATE * DEGREES))
"""E[e | e < TRUNCATE v] / v under the noise alone (E[X; X < t] = k P(chi2(k + 2) < t) for X ~ chi2(k))."""
MEDIAN = float(_CENTRE.median() / DEGREES)
"""median(e) / v under the noise alone."""
SMOOTH = float(_RING.ppf(0.99) / (len(RING_DETAILS) * len(RING)))
"""Ring roughness beyond SMOOTH times the reference variance marks a textured sample (the second pass)."""


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


def level_sets(samples: list[PlaneSamples], reference: Callable[[np.ndarray], np.ndarray] | None = None,
               min_set: int = MIN_SET, max_sets: int = MAX_SETS) -> tuple[LevelSets, np.ndarray]:
    """The level sets of one channel's samples (its site planes' together).

    Args:
        samples: the channel's site planes' samples.
        reference: the noise variance expected at a ring level (clipping included), from a first fit; None for
            the first pass (the smoothest `KEEP` of each set).

    Returns:
        (the level sets, a boolean mask over the concatenated samples: those the sets kept).
    """
    def joined(name):
        return np.concatenate([getattr(s, name) for s in samples]) if samples else np.zeros(0)

    mean, energy, level, roughness = (joined(name) for name in ("mean", "energy", "level", "roughness"))
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
    for members in np.array_split(order, sets):
        if smooth_enough is None:
            count = max(int(round(KEEP * members.size)), 2)
            smooth = members[np.argsort(roughness[members], kind="stable")[:count]]
        else:
            smooth = members[smooth_enough[members]]
        if smooth.size < 2:
            continue
        robust = np.median(energy[smooth]) / MEDIAN
        if not robust > 0:  # a set of identical values (all clipped): nothing to read
            continue
        kept = smooth[energy[smooth] < TRUNCATE * robust]
        if kept.size < 2:
            continue
        variance = float(np.mean(energy[kept]) / TRUNCATED_FACTOR)
        points["mean"].append(float(np.mean(mean[kept])))
        points["variance"].append(variance)
        points["count"].append(kept.size)
        # a block mean of 9 pixels; both point estimates are means over samples STRIDE apart
        points["mean_variance"].append(variance / 9.0 / kept.size)
        points["variance_variance"].append(2.0 * variance**2 * STRIDE_CORRELATION / kept.size)
        used[kept] = True
    return LevelSets(*(np.asarray(points[name], dtype=np.float64) for name in points)), used
