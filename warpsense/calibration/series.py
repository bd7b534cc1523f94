"""The photon-transfer estimate (EMVA 1288) from a series: flat fields two at a time at several exposures, and
dark frames.

A pair of flat fields of one exposure gives one point of the curve per CFA site: its mean, the mean of the two
frames less the dark frames' mean, and its variance, half the variance of the frames' difference (which cancels
what does not change between frames: the scene's unevenness, vignetting, the pixels' fixed gain pattern), less a
code step's quantization variance (step^2 / 12, which the simulator's ADC adds back). Flat fields are paired by
their mean level: sorted by it, a frame goes with the next one when their means agree to `PAIR_TOLERANCE`. Points
within 70% of the white level (EMVA 1288's fitting range) with no pixel at a clip bound in either frame are fitted.

Dark frames (``--dark``) give the read noise directly: half the variance of two darks' difference (or one dark's
variance: fixed-pattern noise included, noted), less the quantization variance; where a dark frame is clipped at
the zero code (a simulated sensor with black at zero), the offset and the read noise whose clipped, quantized
moments (`warpsense.calibration.model.clipped_moments`) are the frame's own. The shot coefficient is then the
weighted slope through the origin of (variance - read^2) against the dark-subtracted mean; without dark frames
the read noise is the weighted line's intercept.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import optimize

from warpsense.calibration.captures import CalibrateError, Capture
from warpsense.calibration.fit import Z95, NoiseFit

PAIR_TOLERANCE = 0.03
"""Two flat fields pair when their means differ by at most this fraction of the larger (and 1e-4 of white)."""
FIT_RANGE = 0.7
"""Points above this fraction of the white level are left out of the fit (EMVA 1288)."""
CLIPPED = 1e-3
"""A frame with more than this fraction of a site's pixels at a clip bound counts as clipped there."""


@dataclass
class SeriesPoint:
    """One point of a channel's photon-transfer curve: a flat pair's (``kind`` "pair") or a dark frame set's
    (``kind`` "dark") mean and variance at one CFA site, the variance's sampling variance, and its files."""

    letter: str
    mean: float
    variance: float
    variance_variance: float
    files: tuple[str, ...]
    kind: str
    used: bool = True


@dataclass
class SeriesEstimate:
    """The series' estimate over all channels (``fit``) and per channel, with its points and pairs."""

    fit: NoiseFit
    channels: dict[str, NoiseFit | None]
    points: list[SeriesPoint]
    pairs: list[tuple[str, str]]
    darks: list[str]
    notes: list[str] = field(default_factory=list)


def pair_flats(flats: list[Capture]) -> tuple[list[tuple[Capture, Capture]], list[tuple[Path, str]]]:
    """Flat fields paired by mean level (see the module docstring); the frames left without a partner come back
    as failures [(path, reason)]."""
    means = sorted(((float(np.mean([np.mean(s.plane) for s in c.sites])), c) for c in flats), key=lambda x: x[0])
    pairs, failures = [], []
    index = 0
    while index < len(means):
        mean, capture = means[index]
        if index + 1 < len(means):
            other_mean, other = means[index + 1]
            same = (other.white_level == capture.white_level and other.pattern == capture.pattern
                    and other.sites[0].plane.shape == capture.sites[0].plane.shape)
            if same and abs(other_mean - mean) <= PAIR_TOLERANCE * max(mean, other_mean) + 1e-4:
                pairs.append((capture, other))
                index += 2
                continue
        failures.append((capture.path, f"{capture.path}: no partner of equal exposure in the series (its mean "
                                        f"level {mean:.4f} of white; a pair's means agree to "
                                        f"{PAIR_TOLERANCE:.0%})"))
        index += 1
    return pairs, failures


def _clipped_fraction(plane: np.ndarray, lower: float, upper: float, step: float) -> float:
    return float(np.mean((plane <= lower + 0.5 * step) | (plane >= upper - 0.5 * step)))


def _censored_fit(values: np.ndarray, lower: float, upper: float, step: float) -> tuple[float, float]:
    """(offset, variance) of dark readings clipped at the zero code: the maximum-likelihood Gaussian whose clipped,
    rounded codes (code k takes the readings within half a step of lower + k step, code 0 all below, the top code
    all above) give the readings' histogram."""
    from scipy.special import ndtr

    top = int(round((upper - lower) / step))
    codes = np.clip(np.round((values - lower) / step), 0, top).astype(np.int64)
    counts = np.bincount(codes - codes.min())
    present = np.nonzero(counts)[0] + codes.min()
    counts = counts[counts > 0]
    edge_low = np.where(present <= 0, -np.inf, lower + (present - 0.5) * step)
    edge_high = np.where(present >= top, np.inf, lower + (present + 0.5) * step)

    def negative_log_likelihood(theta):
        sigma = np.exp(theta[1])
        high, low = (edge_high - theta[0]) / sigma, (edge_low - theta[0]) / sigma
        # log(Phi(high) - Phi(low)) in the tail that keeps precision
        probability = np.where(low > 0, ndtr(-low) - ndtr(-high), ndtr(high) - ndtr(low))
        return -float(np.sum(counts * np.log(np.maximum(probability, 1e-300))))

    mean, spread = float(np.mean(values)), float(np.std(values))
    start = np.array([mean, np.log(max(spread, step / 4))])
    solution = optimize.minimize(negative_log_likelihood, start, method="Nelder-Mead",
                                 options={"xatol": 1e-9, "fatol": 1e-9, "maxiter": 4000})
    return float(solution.x[0]), float(np.exp(2 * solution.x[1]))


def _dark_moments(planes: list[np.ndarray], lower: float, upper: float, step: float) -> tuple[float, float, str]:
    """(offset, read variance, how) of one CFA site's dark frames (see the module docstring)."""
    values = np.concatenate([p.ravel() for p in planes])
    offset = float(np.mean(values))
    if max(_clipped_fraction(p, lower, upper, step) for p in planes) > CLIPPED:
        return (*_censored_fit(values, lower, upper, step), "clipped at the zero code: maximum likelihood over codes")
    if len(planes) >= 2:
        differences = [planes[i].ravel() - planes[i + 1].ravel() for i in range(len(planes) - 1)]
        variance = float(np.mean([np.var(d, ddof=1) for d in differences]) / 2)
        return offset, max(variance - step**2 / 12, 0.0), "frame differences"
    variance = float(np.var(values, ddof=1))
    return offset, max(variance - step**2 / 12, 0.0), "one frame (fixed-pattern noise included)"


def _fit_points(points: list[SeriesPoint], dark: list[SeriesPoint]) -> NoiseFit:
    """The curve through ``points`` (the read noise from ``dark`` where given, see the module docstring)."""
    x = np.array([p.mean for p in points])
    y = np.array([p.variance for p in points])
    w = 1.0 / np.array([p.variance_variance for p in points])
    if dark:
        read_variance = float(np.mean([p.variance for p in dark]))
        read_error = float(np.sqrt(np.sum([p.variance_variance for p in dark])) / len(dark))
        shot = float(np.sum(w * x * (y - read_variance)) / np.sum(w * x * x))
        residuals = (y - read_variance - shot * x) * np.sqrt(w)
        degrees = max(x.size - 1, 1)
        overdispersion = max(1.0, float(np.sum(residuals**2)) / degrees)
        shot_error = float(np.sqrt(overdispersion / np.sum(w * x * x)))
        covariance = np.array([[(shot_error / shot) ** 2, 0.0], [0.0, read_error**2]])
    else:
        design = np.stack([x, np.ones_like(x)], axis=1) * np.sqrt(w)[:, None]
        (shot, read_variance), *_ = np.linalg.lstsq(design, y * np.sqrt(w), rcond=None)
        residuals = y * np.sqrt(w) - design @ np.array([shot, read_variance])
        degrees = max(x.size - 2, 1)
        overdispersion = max(1.0, float(np.sum(residuals**2)) / degrees)
        cov = np.linalg.pinv(design.T @ design) * overdispersion
        shot, read_variance = float(shot), float(read_variance)
        if not shot > 0:
            raise CalibrateError("the series' variance does not grow with its mean: no shot noise to fit (are the "
                                 "flat fields lit, and of different exposures?)")
        read_variance = max(read_variance, 0.0)
        covariance = np.array([[cov[0, 0] / shot**2, cov[0, 1] / shot], [cov[0, 1] / shot, cov[1, 1]]])
        read_error = float(np.sqrt(cov[1, 1]))
    if not shot > 0:
        raise CalibrateError("the series' variance does not grow with its mean above the dark frames' (are the "
                             "flat fields lit?)")
    log_error = float(np.sqrt(covariance[0, 0]))
    shot_interval = (shot * float(np.exp(-Z95 * log_error)), shot * float(np.exp(Z95 * log_error)))
    read_interval = (float(np.sqrt(max(read_variance - Z95 * read_error, 0.0))),
                     float(np.sqrt(read_variance + Z95 * read_error)))
    return NoiseFit(shot, float(np.sqrt(read_variance)), shot_interval, read_interval, len(points) + len(dark),
                    overdispersion, covariance)


def estimate_series(flats: list[Capture], darks: list[Capture]) -> tuple[SeriesEstimate, list[tuple[Path, str]]]:
    """The photon-transfer estimate of a series (see the module docstring).

    Returns:
        (the estimate, the frames left out [(path, reason)]: unpaired flat fields).

    Raises:
        CalibrateError: too few usable points (pairs below the white level's 70%, unclipped) to fit a curve.
    """
    pairs, failures = pair_flats(flats)
    notes = []
    reference = flats[0] if flats else None
    for capture in [*flats, *darks]:
        if reference is not None and (capture.pattern != reference.pattern
                                      or capture.white_level != reference.white_level):
            raise CalibrateError(f"{capture.path}: a series is one sensor's: its CFA {capture.pattern} and white "
                                 f"level {capture.white_level:g} differ from {reference.path}'s")
    dark_points, offsets = [], {}
    for index in range(len(reference.sites) if reference else 0):
        if not darks:
            break
        site = reference.sites[index]
        planes = [d.sites[index].plane for d in darks]
        offset, variance, how = _dark_moments(planes, site.lower, site.upper, site.step)
        offsets[index] = offset
        count = planes[0].size * max(len(planes) - 1, 1)
        dark_points.append(SeriesPoint(site.letter, offset, variance, 2 * variance**2 / max(count - 1, 1),
                                       tuple(str(d.path) for d in darks), "dark"))
        if index == 0:
            notes.append(f"read noise from {len(darks)} dark frame(s): {how}")
    points = []
    for first, second in pairs:
        for index, site in enumerate(first.sites):
            a, b = site.plane, second.sites[index].plane
            mean = float(np.mean(a) + np.mean(b)) / 2 - offsets.get(index, 0.0)
            variance = float(np.var(a - b, ddof=1)) / 2 - site.step**2 / 12
            clipped = max(_clipped_fraction(p, site.lower, site.upper, site.step) for p in (a, b))
            used = clipped <= CLIPPED and mean + offsets.get(index, 0.0) <= FIT_RANGE * site.upper and mean > 0
            points.append(SeriesPoint(site.letter, mean, variance, 2 * variance**2 / max(a.size - 1, 1),
                                      (str(first.path), str(second.path)), "pair", used))
    usable = [p for p in points if p.used]
    letters = list(dict.fromkeys(p.letter for p in points))
    if len({p.files for p in usable}) < (1 if darks else 2):
        raise CalibrateError(f"the series gives {len({p.files for p in usable})} usable flat pair(s) (below "
                             f"{FIT_RANGE:.0%} of white, unclipped), at least {1 if darks else 2} needed "
                             f"{'with' if darks else 'without'} dark frames; flat fields: "
                             f"{', '.join(str(c.path) for c in flats) or 'none'}")
    fit = _fit_points(usable, dark_points)
    channels = {}
    for letter in letters:
        mine = [p for p in usable if p.letter == letter]
        try:
            channels[letter] = _fit_points(mine, [p for p in dark_points if p.letter == letter]) if mine else None
        except CalibrateError:
            channels[letter] = None
    return (SeriesEstimate(fit, channels, points + dark_points, [(str(a.path), str(b.path)) for a, b in pairs],
                           [str(d.path) for d in darks], notes), failures)
