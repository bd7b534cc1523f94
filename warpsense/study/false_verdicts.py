"""The verdict rules' false-verdict rate with the same camera twice (A/A), simulated from measured seed variance.

A camera entered twice (a twin with its own seeds: ``seed_offset``) differs from itself only by its training's
randomness: per fold f and seed s the paired difference is d = e_A - e_B, two independent draws of the within-fold
seed residual of one camera's mIoU (the fold's own difficulty cancels in the pair). `seed_residuals` measures those
residuals in finished studies' run directories (the archives of docs/records: each cell's evaluation.json), and
`simulate` draws A/A studies from them, normal with the measured standard deviation (`normal_differences`) or by
resampling the measured residuals themselves, with their tails (`resampled_differences`), and counts how often each
rule calls a difference:

- the fixed rule (`warpsense.study.report._verdict`) at S seeds: the 95% paired t interval over the S x F (fold,
  seed) pairs excludes 0 (the report also asks the frame bootstrap to exclude 0, which can only lower the rate: the
  simulated rate bounds the rule's from above);
- the fixed interval looked at after every seed, stopping at the first that excludes 0 ("peeking": what the
  sequential study would do without a boundary);
- the sequential rule (`warpsense.study.sequential`): the Pocock-type repeated interval, stopping at a verdict, at the
  tolerance or at max_seeds; per stopping time, how many A/A comparisons stop there, how many of those with a false
  verdict, and the false verdicts up to that look.

`tools/aa_simulation.py` runs it on the archives and prints docs/results.md's table.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy import stats

from warpsense.study.archives import archive_cells
from warpsense.study.sequential import SequentialRule, critical_value, nominal_level


def archive_scores(archives: list[str | Path]) -> list[dict]:
    """Every finished cell of ``archives`` with its score (`warpsense.study.archives.archive_cells`)."""
    return archive_cells(archives)


def seed_residuals(rows: list[dict]) -> dict:
    """The within-fold seed spread of one camera's mIoU, from `archive_scores`' rows.

    Per group (study directory, camera, light, fold) of >= 2 seeds, each run's residual from the group's mean,
    scaled by sqrt(n / (n - 1)) so that its variance is the seeds' (n seeds per group); and, for contrast, the
    spread of the paired differences between two cameras of one study at the same fold and seed (they share the
    seed's initialisation and data order, so they can be less spread than an A/A twin's, whose seeds differ).

    Returns:
        {"sd": pooled within-fold seed standard deviation (sum of squares over sum of n - 1), "groups", "runs",
        "residuals": [R] scaled residuals, "by_fold": {fold: residuals}, "directories": {study directory: runs used},
        "paired_sd": pooled within-fold standard deviation of the paired differences between two cameras of one
        study at the same seed, "paired_groups"}.
    """
    groups: dict = {}
    for row in rows:
        groups.setdefault((row["archive"], row["directory"], row["camera"], row["light"], row["fold"]), {})[
            row["seed"]] = row["miou"]
    residuals, by_fold, squares, dof, directories = [], {}, 0.0, 0, {}
    for (archive, directory, _camera, _light, fold), scores in sorted(groups.items()):
        if len(scores) < 2:
            continue
        values = np.array([scores[seed] for seed in sorted(scores)])
        centred = values - values.mean()
        squares += float((centred ** 2).sum())
        dof += len(values) - 1
        scaled = centred * math.sqrt(len(values) / (len(values) - 1))
        residuals += scaled.tolist()
        by_fold.setdefault(fold, []).extend(scaled.tolist())
        key = f"{archive}:{directory}"
        directories[key] = directories.get(key, 0) + len(values)
    if not dof:
        raise ValueError("seed_residuals: no camera has two seeds of one fold in these archives")
    paired_squares, paired_dof, paired_groups = 0.0, 0, 0
    studies: dict = {}
    for (archive, directory, camera, light, fold), scores in groups.items():
        studies.setdefault((archive, directory, light, fold), {})[camera] = scores
    for cameras in studies.values():
        names = sorted(cameras)
        for a, b in zip(names, names[1:]):  # neighbouring cameras: each camera's runs in at most two pairs
            common = sorted(set(cameras[a]) & set(cameras[b]))
            if len(common) < 2:
                continue
            differences = np.array([cameras[a][s] - cameras[b][s] for s in common])
            paired_squares += float(((differences - differences.mean()) ** 2).sum())
            paired_dof += len(common) - 1
            paired_groups += 1
    return {"sd": math.sqrt(squares / dof), "groups": sum(1 for s in groups.values() if len(s) >= 2),
            "runs": len(residuals), "residuals": np.array(residuals),
            "by_fold": {fold: np.array(values) for fold, values in by_fold.items()}, "directories": directories,
            "paired_sd": math.sqrt(paired_squares / paired_dof) if paired_dof else None,
            "paired_groups": paired_groups}


def normal_differences(sd: float) -> Callable:
    """A/A paired differences e_A - e_B with e ~ N(0, sd^2): draw(generator, shape) -> array."""
    return lambda generator, shape: generator.normal(0.0, sd, shape) - generator.normal(0.0, sd, shape)


def resampled_differences(residuals) -> Callable:
    """A/A paired differences e_A - e_B with e resampled (with replacement) from measured seed ``residuals``:
    their tails, not a normal's."""
    pool = np.asarray(residuals, dtype=np.float64)
    return lambda generator, shape: generator.choice(pool, shape) - generator.choice(pool, shape)


def resampled_by_fold(by_fold: dict) -> Callable:
    """As `resampled_differences`, each fold's pairs from that fold's own residuals (`seed_residuals`' ``by_fold``,
    in sorted order): folds whose seeds spread differently (CamVid's drive folds: 0.007-0.020) stay so. The shape's
    last axis must be the number of folds."""
    pools = [np.asarray(by_fold[fold], dtype=np.float64) for fold in sorted(by_fold)]

    def draw(generator, shape):
        if shape[-1] != len(pools):
            raise ValueError(f"resampled_by_fold: {len(pools)} folds' residuals, asked for {shape[-1]} folds")
        return np.stack([generator.choice(pool, shape[:-1]) - generator.choice(pool, shape[:-1]) for pool in pools],
                        axis=-1)

    return draw


def simulate(draw: Callable, folds: int, rule: SequentialRule, replicates: int = 20_000, seed: int = 0) -> dict:
    """False verdicts of A/A studies of ``folds`` folds, up to ``rule.max_seeds`` seeds.

    Args:
        draw: draw(generator, shape) -> paired differences of shape [replicates, seeds, folds] under A/A.
        folds: pairs per seed (the plan's folds; 1 without).
        rule: the sequential rule (its min_seeds, max_seeds, tolerance; level the intervals' confidence).
        replicates: simulated A/A comparisons.
        seed: the simulation's random seed.

    Returns:
        {"replicates", "folds", "nominal_level" (the sequential rule's a'), "fixed": per seeds S
        (min_seeds..max_seeds) the share of A/A comparisons the fixed 95% t interval over S x folds pairs calls,
        "peeking": per look the share called at or before it by the fixed interval looked at after every seed,
        "sequential": per look {"seeds", "stopped" (share stopping there), "false" (share stopping there with a
        verdict), "false_given_stop" (false / stopped), "cumulative" (false verdicts up to this look)}, "mean_seeds":
        seeds a sequential A/A comparison trains on average, "overall": the sequential rule's false-verdict rate,
        "any_look": the share whose repeated interval excludes 0 at some look, stopped there or not: the bound on
        the false-verdict rate of any rule for when to stop among the planned looks}.
    """
    generator = np.random.default_rng(seed)
    differences = np.asarray(draw(generator, (replicates, rule.max_seeds, folds)), dtype=np.float64)
    looks = rule.looks(folds)
    nominal = nominal_level(looks, rule.level)
    alpha = 1 - rule.level
    fixed, peeking, sequential = [], [], []
    active = np.ones(replicates, dtype=bool)  # sequential comparisons not stopped yet
    peeked = np.zeros(replicates, dtype=bool)
    crossed = np.zeros(replicates, dtype=bool)  # the repeated interval excludes 0 at some look, stopped or not
    cumulative, seeds_used = 0.0, np.zeros(replicates)
    for seeds, n in zip(range(rule.min_seeds, rule.max_seeds + 1), looks):
        pairs = differences[:, :seeds, :].reshape(replicates, -1)
        mean = pairs.mean(axis=1)
        error = pairs.std(axis=1, ddof=1) / math.sqrt(n)
        excluded = np.abs(mean) > stats.t.ppf(1 - alpha / 2, n - 1) * error
        fixed.append({"seeds": seeds, "pairs": n, "rate": float(excluded.mean())})
        peeked |= excluded
        peeking.append({"seeds": seeds, "cumulative": float(peeked.mean())})
        half = critical_value(n, nominal) * error
        called = np.abs(mean) > half
        crossed |= called
        stop = active & (called | (half <= rule.tolerance) | (seeds == rule.max_seeds))
        false = stop & called
        cumulative += float(false.mean())
        seeds_used[stop] = seeds
        sequential.append({"seeds": seeds, "stopped": float(stop.mean()), "false": float(false.mean()),
                           "false_given_stop": float(false.sum() / stop.sum()) if stop.any() else None,
                           "cumulative": cumulative})
        active &= ~stop
    return {"replicates": replicates, "folds": folds, "nominal_level": nominal, "fixed": fixed, "peeking": peeking,
            "sequential": sequential, "mean_seeds": float(seeds_used.mean()), "overall": cumulative,
            "any_look": float(crossed.mean())}


def standard_error(rate: float, replicates: int) -> float:
    """The Monte Carlo standard error of a simulated rate."""
    return math.sqrt(max(rate * (1 - rate), 1e-12) / replicates)


def table_lines(rows: list[tuple[str, dict]]) -> list[str]:
    """docs/results.md's table of `simulate` results, one row per (label of the A/A data, result): the fixed rule at
    min and max seeds, peeking at max, the sequential rule's rate and its bound for any stopping time (`simulate`'s
    ``any_look``), the seeds a comparison trains."""
    lines = ["| A/A data | folds | fixed rule, min seeds | fixed rule, max seeds | fixed interval looked at every seed "
             "| sequential rule | sequential, any stopping time (bound) | seeds per comparison |",
             "|---|---|---|---|---|---|---|---|"]
    for label, result in rows:
        lines.append(f"| {label} | {result['folds']} | {result['fixed'][0]['rate']:.3f} | "
                     f"{result['fixed'][-1]['rate']:.3f} | {result['peeking'][-1]['cumulative']:.3f} | "
                     f"{result['overall']:.3f} | {result['any_look']:.3f} | {result['mean_seeds']:.2f} |")
    return lines


def to_json(value):
    """``value`` with numpy arrays as lists (for --json)."""
    if isinstance(value, dict):
        return {str(key): to_json(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(item) for item in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value
