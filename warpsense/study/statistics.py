"""The statistics of a camera study: Student-t intervals over seeds (clustered by fold with sequence folds), paired
differences over (fold, seed), and a moving-block bootstrap of mIoU differences that resamples frames within their
sequences, from per-image confusion counts."""

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


FEWEST_VALUES = 3
"""The fewest independent values (seeds; with several folds, the folds' means) whose t interval says something
about the mean. Over 2 the 95% t quantile is 12.71: the interval is 12.7 times the two values' distance wide
(0.0723 [-0.2872, 0.4319] for two runs 0.04 apart); over 3 it is 4.30, over 5 2.78 (1.96 with many). The text marks
an interval over fewer (`interval_text`) and the report says what the mark means (`few_values_note`)."""

SCORE_BOUNDS = (0.0, 1.0)
"""The range of a score (mIoU, IoU); a difference of two scores lies in (-1, 1)."""


def independent_values(record: dict) -> int:
    """The independent values an interval record is over: the folds where it is clustered by several
    (`fold_interval`), otherwise its n."""
    folds = record.get("folds") or 0
    return folds if folds > 1 else record["n"]


def too_few_mark(record: dict) -> str:
    """" (n=2, too few)" (" (2 folds, too few)" for a clustered one) where an interval is over fewer than
    `FEWEST_VALUES` independent values; "" otherwise."""
    values = independent_values(record)
    if record["low"] is None or values >= FEWEST_VALUES:
        return ""
    return f" ({values} folds, too few)" if (record.get("folds") or 0) > 1 else f" (n={values}, too few)"


def bounded(record: dict, signed: bool = False) -> tuple[float, float]:
    """(low, high) of an interval record clipped to the range of what it bounds: a score's [0, 1], a difference's
    [-1, 1] with ``signed``. The t interval is symmetric about the mean, so over few or spread values it crosses
    the range (a mean mIoU of 0.07 over 2 seeds: [-0.29, 0.43]); the mean itself cannot. The record keeps the t
    interval as computed."""
    low, high = (-SCORE_BOUNDS[1], SCORE_BOUNDS[1]) if signed else SCORE_BOUNDS
    return max(record["low"], low), min(record["high"], high)


def interval_text(record: dict | None, signed: bool = False) -> str:
    """"mean [low, high]" of a score (or, ``signed``, a difference of scores, with "+" signs) to 4 decimals, the
    interval clipped to the score's range (`bounded`) and marked where it is over too few values (`too_few_mark`);
    "-" for no record; "[n=1, no interval]"."""
    if record is None:
        return "-"
    sign = "+" if signed else ""
    if record["low"] is None:
        return f"{record['mean']:{sign}.4f} [n=1, no interval]"
    low, high = bounded(record, signed)
    return f"{record['mean']:{sign}.4f} [{low:{sign}.4f}, {high:{sign}.4f}]{too_few_mark(record)}"


def _intervals(value) -> list[dict]:
    """Every interval record (a dict with mean, low, high and n) anywhere in a nested record, but those under a
    ``per_class...`` key (the text prints their means only)."""
    if isinstance(value, dict):
        if {"mean", "low", "high", "n"} <= set(value):
            return [value]
        return [interval for key, item in value.items() if not str(key).startswith("per_class")
                for interval in _intervals(item)]
    if isinstance(value, list):
        return [interval for item in value for interval in _intervals(item)]
    return []


def few_values_note(record: dict, level: float = LEVEL) -> list[str]:
    """The lines that say what `too_few_mark` means, where an interval of ``record`` (a report's, or any nested
    record) carries it; none otherwise."""
    counts = sorted({independent_values(i) for i in _intervals(record) if too_few_mark(i)})
    if not counts:
        return []
    quantiles = {n: stats.t.ppf(0.5 + level / 2, n - 1) for n in (*counts, FEWEST_VALUES, 5)}
    over = ", ".join(f"{quantiles[n]:.2f} over {n}" for n in counts)
    return [f"note: 'too few' marks an interval over fewer than {FEWEST_VALUES} independent values (seeds; with "
            f"several folds, the folds' means): its {level:.0%} t quantile is {over}, so the interval is many times "
            f"the values' spread and says little; an interval takes at least {FEWEST_VALUES} values (t "
            f"{quantiles[FEWEST_VALUES]:.2f}), better 5 ({quantiles[5]:.2f}): add seeds (study.seeds) or folds"]


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


def fold_interval(values: dict, level: float = LEVEL) -> dict:
    """Mean of a camera's scores over (fold, seed) cells with an interval clustered by fold.

    Args:
        values: score per (fold, seed) key; fold "" (one fold: the study has none).

    Returns:
        {"mean" (over every cell), "low", "high", "n" (cells), "folds"}: with one fold the Student-t interval over its
        seeds; with several, the t interval over the folds' means (F - 1 degrees of freedom): each fold is another
        drive, and its seeds share it, so the folds, not the cells, are the independent samples of "a new drive".
    """
    if not values:
        raise ValueError("fold_interval: no values")
    folds: dict = {}
    for (fold, _seed), value in values.items():
        folds.setdefault(fold, []).append(value)
    mean = float(np.mean(list(values.values())))
    if len(folds) == 1:
        interval = t_interval(list(values.values()), level)
    else:
        interval = t_interval([np.mean(scores) for scores in folds.values()], level)
        shift = mean - interval["mean"]  # unequal seeds per fold: the interval is centred on the cells' mean
        interval = {**interval, "low": interval["low"] + shift, "high": interval["high"] + shift}
    return {**interval, "mean": mean, "n": len(values), "folds": len(folds)}


def block_weights(sequences: list, block: int, resamples: int, generator: np.random.Generator) -> np.ndarray:
    """Moving-block bootstrap weights [resamples, N] for N frames in their order, resampled within each sequence.

    Each sequence of n frames (those of ``sequences`` with its name, in order) is rebuilt from ceil(n / b) blocks of
    b = min(block, n // 2) consecutive frames (at least 1), each starting at a uniform position of the n - b + 1,
    truncated to n frames (Kuensch 1989): neighbouring frames of one drive are alike, so they are drawn together, and
    a sequence keeps its size, so no sequence stands in for another. A sequence of at most ``block`` frames is drawn
    in two blocks or more: as one block it would be the same draw in every resample (a zero-width interval). Weight
    [r, i]: how often frame i is drawn in resample r."""
    sequences = list(sequences)
    weights = np.zeros((resamples, len(sequences)))
    for name in dict.fromkeys(sequences):
        frames = np.array([i for i, other in enumerate(sequences) if other == name])
        n = len(frames)
        length = max(1, min(block, n // 2))
        blocks = -(-n // length)
        starts = generator.integers(0, n - length + 1, size=(resamples, blocks))
        drawn = (starts[:, :, None] + np.arange(length)).reshape(resamples, -1)[:, :n]
        flat = (np.arange(resamples)[:, None] * n + drawn).ravel()
        weights[:, frames] = np.bincount(flat, minlength=resamples * n).reshape(resamples, n)
    return weights


def block_bootstrap_difference(runs: list[tuple], sequences: dict, block: int = 10, resamples: int = 2000,
                               seed: int = 0, level: float = LEVEL) -> dict:
    """Clustered (moving-block, within-sequence) bootstrap of the mean mIoU difference between paired runs.

    Args:
        runs: (counts, reference, frames) per pair of runs (a camera's and the reference's, same fold and seed):
            per-image (TP, FP, FN) counts [N, K, 3] of both on the same N frames, and the key of those frames.
        sequences: per frames key, the sequence of each of its N frames in evaluation order. Every pair judged on
            the same frames (every seed of a fold) is resampled with the same draws (`block_weights`).
        block: frames per block (consecutive frames of one sequence drawn together).

    Returns:
        {"mean": the mean over pairs of the mIoU difference on all frames (the paired mean), "low", "high":
        percentile interval of the resampled mean differences, "resamples", "block"}.
    """
    if not runs:
        raise ValueError("block_bootstrap_difference: no pairs of runs")
    generator = np.random.default_rng(seed)
    weights = {key: block_weights(sequences[key], block, resamples, generator) for key in dict.fromkeys(
        frames for _, _, frames in runs)}
    differences, point = np.zeros(resamples), 0.0
    for counts, reference, frames in runs:
        counts, reference = np.asarray(counts, dtype=np.float64), np.asarray(reference, dtype=np.float64)
        if counts.shape != reference.shape or counts.ndim != 3 or counts.shape[0] != len(sequences[frames]):
            raise ValueError(f"block_bootstrap_difference: expected two [N, K, 3] arrays of one shape on the "
                             f"{len(sequences[frames])} frames of {frames!r}, got {counts.shape} and {reference.shape}")
        drawn = [(weights[frames] @ array.reshape(len(array), -1)).reshape(resamples, *array.shape[1:])
                 for array in (counts, reference)]
        differences += miou_from_counts(drawn[0]) - miou_from_counts(drawn[1])
        point += float(miou_from_counts(counts.sum(0)) - miou_from_counts(reference.sum(0)))
    differences /= len(runs)
    tail = (1 - level) / 2 * 100
    low, high = np.percentile(differences, [tail, 100 - tail])
    return {"mean": point / len(runs), "low": float(low), "high": float(high), "resamples": resamples,
            "block": block}
