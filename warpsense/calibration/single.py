"""The single-capture estimate (Foi et al. 2008, re-derived): local samples of smooth regions, level sets, and a
clipping-aware fit of variance = shot * y + read^2, per CFA channel and over all channels and captures together.

Per capture, per CFA site: samples (`local.plane_samples`), then two passes. The first takes the smoothest part of
each level set (`levels.KEEP`) and fits a curve over the capture's sites together; the second keeps every sample
whose ring is as smooth as that curve's noise allows and fits again: the capture's estimate. A channel's estimate
fits its sites' level sets alone; several captures of one sensor fit their level sets together.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from warpsense.calibration.captures import CalibrateError, Capture, Site
from warpsense.calibration.fit import FitError, Group, NoiseFit, fit_noise
from warpsense.calibration.levels import level_sets
from warpsense.calibration.local import plane_samples

MIN_SAMPLES = 1000
"""Least number of smooth samples (3 x 3 blocks) a capture must give, over its sites."""
MIN_SETS = 6
"""Least number of level sets a capture must give, over its sites."""


@dataclass
class SiteSets:
    """The level sets of one filter of one capture (its sites together, e.g. a Bayer tile's two greens, where they
    share the ADC's range; ``site`` is the first of them), and how many of its samples they kept out of how many."""

    site: Site
    group: Group
    kept: int
    samples: int


@dataclass
class CaptureEstimate:
    """One capture's estimate: over its channels together (``fit``) and per channel (None: too few sets)."""

    capture: Capture
    fit: NoiseFit
    channels: dict[str, NoiseFit | None]
    sites: list[SiteSets]
    notes: list[str] = field(default_factory=list)

    def regions(self) -> dict:
        """Per channel, the smooth regions the fit read: samples kept (blocks of 3 x 3 pixels of the channel's
        plane, in 9 x 9 windows), of how many, the level sets and their range of levels."""
        regions = {}
        for letter in self.capture.letters:
            mine = [s for s in self.sites if s.site.letter == letter]
            means = np.concatenate([s.group.sets.mean for s in mine])
            regions[letter] = {"samples": int(sum(s.kept for s in mine)), "of": int(sum(s.samples for s in mine)),
                               "level_sets": int(means.size),
                               "levels": [float(means.min()), float(means.max())] if means.size else None}
        return regions


def _fit_or_none(groups: list[Group]) -> NoiseFit | None:
    try:
        return fit_noise(groups)
    except FitError:
        return None


def estimate_capture(capture: Capture) -> CaptureEstimate:
    """Estimate one capture's noise curve (see the module docstring).

    Raises:
        CalibrateError: too few smooth pixels (the message names the file, the samples and sets found and the
            least needed).
    """
    # the sites of one filter and one ADC range (the two greens of a Bayer tile) share their level sets
    channels_samples: dict[tuple, tuple[Site, list]] = {}
    for site in capture.sites:
        key = (site.letter, site.lower, site.upper, site.step)
        channels_samples.setdefault(key, (site, []))[1].append(plane_samples(site.plane, site.lower, site.upper,
                                                                             site.step))
    samples = list(channels_samples.values())

    def too_few(kept: int, sets: int) -> CalibrateError:
        return CalibrateError(f"{capture.path}: too few smooth pixels: {kept} smooth samples (3 x 3 blocks of a "
                              f"colour channel) in {sets} level sets, at least {MIN_SAMPLES} in {MIN_SETS} needed "
                              "(a larger capture, or one with flat regions)")

    first_groups = [Group(level_sets(planes, lower=site.lower, upper=site.upper, step=site.step)[0], site.lower,
                          site.upper, site.step) for site, planes in samples]
    try:
        first = fit_noise(first_groups)
    except FitError:
        raise too_few(int(sum(np.sum(g.sets.count) for g in first_groups)),
                      sum(len(g.sets) for g in first_groups)) from None
    sites = []
    # the first curve with its read noise at the top of its interval: where the first pass could not see the read
    # noise (few dark samples among its smoothest), a reference at its estimate would reject every dark sample
    cautious = NoiseFit(first.shot, first.read_interval[1], first.shot_interval, first.read_interval, first.points,
                        first.overdispersion, first.covariance)
    for site, planes in samples:
        def reference(level, site=site):
            # the curve at the levels' quantiles, interpolated: the exact sums over codes at every sample would cost
            # seconds, and quantiles are dense where the samples are (near black, where the curve bends)
            grid = np.unique(np.quantile(level, np.linspace(0, 1, 513))) if level.size else np.zeros(1)
            return np.interp(level, grid, cautious.variance(grid, site.lower, site.upper, site.step))

        sets, used = level_sets(planes, reference, lower=site.lower, upper=site.upper, step=site.step)
        sites.append(SiteSets(site, Group(sets, site.lower, site.upper, site.step), int(used.sum()),
                              sum(len(plane) for plane in planes)))
    kept = sum(s.kept for s in sites)
    count = sum(len(s.group.sets) for s in sites)
    if kept < MIN_SAMPLES or count < MIN_SETS:
        raise too_few(kept, count)
    fit = fit_noise([s.group for s in sites])
    channels = {letter: _fit_or_none([s.group for s in sites if s.site.letter == letter])
                for letter in capture.letters}
    notes = []
    if fit.read_interval[0] == 0.0:
        darkest = min(float(s.group.sets.mean.min()) for s in sites if len(s.group.sets))
        notes.append(f"{capture.path}: the read noise is not resolved from zero (95% interval from 0): its darkest "
                     f"smooth regions are at {darkest:.2%} of the white level, where the shot noise hides it"
                     + (" (or its black level is off: nothing reads darker)" if darkest > 0.02 else ""))
    return CaptureEstimate(capture, fit, channels, sites, notes)


def fit_together(estimates: list[CaptureEstimate]) -> tuple[NoiseFit, dict[str, NoiseFit | None]]:
    """One curve over several captures' level sets (each with its own ADC bounds), and one per channel."""
    fit = fit_noise([s.group for e in estimates for s in e.sites])
    letters = list(dict.fromkeys(letter for e in estimates for letter in e.capture.letters))
    channels = {letter: _fit_or_none([s.group for e in estimates for s in e.sites if s.site.letter == letter])
                for letter in letters}
    return fit, channels
