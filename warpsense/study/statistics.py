"""The statistics of a camera study: Student-t intervals over seeds, paired differences, and an image-level
bootstrap of mIoU differences from per-image confusion counts."""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

LEVEL = 0.95
"""Confidence level of every interval."""


def t_interval(values, level: float = LEVEL) -> dict:
    """Mean of ``values`` with its two-sided Student-t confidence interval (n - 1 degrees of freedom).

    Returns {"mean", "low", "high", "n"}; with one value the interval is unknown (low = high = None)."""
    values = np.asarray(values, dtype=np.float64)
    n = len(values)
    if n == 0:
        raise ValueError("t_interval: no values")
    mean = float(values.mean())
    if n < 2:
        return {"mean": mean, "low": None, "high": None, "n": n}
    half = float(stats.t.ppf(0.5 + level / 2, n - 1) * values.std(ddof=1) / math.sqrt(n))
    return {"mean": mean, "low": mean - half, "high": mean + half, "n": n}


def paired_difference(values: dict, reference: dict, level: float = LEVEL) -> dict:
    """Mean of ``values[k] - reference[k]`` over the keys (seeds) both have, with its t interval: the paired
    comparison, which removes what a seed shares between the two runs (initialisation, data order). ``higher`` and
    ``lower`` count the seeds on each side of 0 (a sign count that a wide interval hides)."""
    keys = sorted(set(values) & set(reference))
    if not keys:
        raise ValueError("paired_difference: no common seeds")
    differences = [values[k] - reference[k] for k in keys]
    return {**t_interval(differences, level), "seeds": keys,
            "higher": sum(d > 0 for d in differences), "lower": sum(d < 0 for d in differences)}


def distinguishable(interval: dict) -> bool | None:
    """Whether an interval excludes 0 (None when it is unknown)."""
    if interval["low"] is None:
        return None
    return interval["low"] > 0 or interval["high"] < 0


def iou_from_counts(counts: np.ndarray) -> np.ndarray:
    """Per-class IoU from (TP, FP, FN) counts [..., K, 3]: TP / (TP + FP + FN), NaN where the class is neither in
    the labels nor in the predictions (as `warpsense.train.metrics.ConfusionMatrix`)."""
    counts = np.asarray(counts, dtype=np.float64)
    union = counts.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, counts[..., 0] / union, np.nan)


def miou_from_counts(counts: np.ndarray) -> np.ndarray:
    """mIoU [...] over the classes present, from (TP, FP, FN) counts [..., K, 3] summed over images."""
    iou = iou_from_counts(counts)
    present = ~np.isnan(iou)
    total = np.where(present, iou, 0).sum(-1)
    count = present.sum(-1)
    return np.where(count > 0, total / np.maximum(count, 1), 0.0)


def bootstrap_difference(counts: np.ndarray, reference: np.ndarray, resamples: int = 2000, seed: int = 0,
                         level: float = LEVEL) -> dict:
    """Image-level bootstrap of the mIoU difference between two cameras judged on the same images.

    Args:
        counts, reference: per-image (TP, FP, FN) counts [S, N, K, 3] of S paired runs (seeds) on the same N
            images, in the same order.
        resamples: bootstrap draws; each draws N images with replacement (the same images for every run and both
            cameras) and recomputes each run's mIoU from the summed counts.

    Returns:
        {"mean": the difference of the seed-mean mIoUs on all images, "low", "high": percentile interval of the
        resampled differences, "resamples"}.
    """
    counts = np.asarray(counts, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if counts.shape != reference.shape or counts.ndim != 4:
        raise ValueError(f"bootstrap_difference: expected two [S, N, K, 3] arrays of one shape, got {counts.shape} "
                         f"and {reference.shape}")
    runs, images, classes, _ = counts.shape
    generator = np.random.default_rng(seed)
    weights = generator.multinomial(images, np.full(images, 1.0 / images), size=resamples).astype(np.float64)
    flat = lambda array: array.transpose(1, 0, 2, 3).reshape(images, -1)  # noqa: E731 [N, S*K*3]
    resampled = [(weights @ flat(array)).reshape(resamples, runs, classes, 3) for array in (counts, reference)]
    differences = (miou_from_counts(resampled[0]) - miou_from_counts(resampled[1])).mean(axis=1)
    point = float((miou_from_counts(counts.sum(1)) - miou_from_counts(reference.sum(1))).mean())
    tail = (1 - level) / 2 * 100
    low, high = np.percentile(differences, [tail, 100 - tail])
    return {"mean": point, "low": float(low), "high": float(high), "resamples": resamples}
