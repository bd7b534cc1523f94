"""Sequential verdicts: a comparison gets another seed only while it is unsettled, and its error rate holds under
that optional stopping.

A plan's ``study.sequential = {min_seeds, max_seeds, tolerance}`` trains ``min_seeds`` seeds of every cell, then
looks at each comparison with the reference camera after every further seed (each look adds one seed's pairs, one
per fold): it goes on only while its interval holds 0 and is wider than ``tolerance`` on each side, so it stops
once the interval excludes 0 (a verdict where the bootstrap agrees), or once it holds 0 within the tolerance (the
smallest difference it could call is below what matters), or at ``max_seeds``.

Why a group-sequential boundary. Looking after every seed and stopping on a significant interval makes the fixed 95% t
interval call a camera different from itself 12-15% of the time instead of 5% (the A/A simulation, docs/results.md: the
rate of a "difference" between one camera and itself grows with every look). Two fixes keep the rate: an anytime-valid
confidence sequence (Howard, Ramdas, McAuliffe and Sekhon 2021, Ann. Statist. 49: valid at any number of looks and any
stopping rule) or a group-sequential boundary (Pocock 1977, Biometrika 64; Jennison and Turnbull 2000, "Group Sequential
Methods", ch. 2-3: valid for the looks planned). The looks here are planned (one a seed, from ``min_seeds`` to
``max_seeds``) and few (1-10), the paired differences are Gaussian-like with an unknown variance estimated from 5-40
pairs, and the cost of a wider interval is GPU hours: a confidence sequence pays for looks that never happen (the
two-sided normal-mixture boundary of Howard et al., even with a known variance and tuned for 15 pairs, is 1.87x the
fixed 95% interval's half-width at 15 pairs), the Pocock boundary only for the planned ones (1.27x the fixed t
interval's at the first of 6 looks of 15-40 pairs: 5 folds x 3-8 seeds). So: a Pocock-type boundary on the paired t
statistic, one nominal two-sided level a' at every look (Jennison and Turnbull's "significance level" form for t
statistics, whose degrees of freedom grow with the looks), with a' calibrated so that a camera compared with itself
crosses at some look with probability at most 1 - level. The interval at a look, mean +- t_{1-a'/2, n-1} s / sqrt(n), is
a repeated confidence interval (Jennison and Turnbull 1984): all looks' intervals cover the true difference together
with probability >= level, so the interval where the comparison stopped keeps its level whatever the stopping rule
(stopping early for ``tolerance`` only removes chances to cross). The report's other interval, the block bootstrap over
frames, stays a condition of the verdict as in the fixed rule: requiring both can only lower the error rate.

Calibration (`nominal_level`): under the null the paired t statistics of the looks have a joint law that depends on
the looks' sizes alone (not on the mean or the variance), so it is simulated once per set of looks: per replicate
and per look's group of m new pairs, the group's sum ~ N(0, m) and its within-group sum of squares ~ chi2(m - 1)
(the sufficient statistics of m standard normal pairs), from which every look's t statistic follows exactly; a' is
the largest level at which at most a share 1 - level of the replicates, less twice the share's Monte Carlo standard
error, cross at some look: with 1,000,000 replicates 0.0496 of them for 5%, so that the true crossing probability is
at most 5% with 97.5% confidence (a calibration aimed at 5% itself landed at 5.07% by another simulation's count);
a fixed seed makes a' a function of the looks (the same on every machine, cached per process). The crossing
probability falls as a' falls, so a' is found by bisection on the simulated |t| statistics.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import stats

from warpsense.study.statistics import LEVEL, distinguishable

REPLICATES = 1_000_000
"""Null replicates of the calibration (`nominal_level`)."""

CALIBRATION_SEED = 20210601
"""The calibration's random seed: a' is a fixed function of the looks."""

SEQUENTIAL_KEYS = {"min_seeds": int, "max_seeds": int, "tolerance": (int, float)}
"""The keys of a plan's ``study.sequential`` table, and their types."""

NOT_DISTINGUISHABLE = "not distinguishable"


@dataclass(frozen=True)
class SequentialRule:
    """A plan's ``study.sequential``: ``min_seeds`` seeds for every comparison, one more at a time while it is
    unsettled, at most ``max_seeds``; settled once its interval holds 0 and its half-width is <= ``tolerance``
    (mIoU, 0..1), or with a verdict. ``level``: the confidence of the repeated intervals."""

    min_seeds: int
    max_seeds: int
    tolerance: float
    level: float = LEVEL

    def looks(self, pairs_per_seed: int) -> tuple[int, ...]:
        """The planned number of pairs at each look: ``pairs_per_seed`` (the plan's folds, 1 without) x seeds, for
        min_seeds..max_seeds seeds."""
        return tuple(pairs_per_seed * seeds for seeds in range(self.min_seeds, self.max_seeds + 1))

    def to_dict(self) -> dict:
        return {"min_seeds": self.min_seeds, "max_seeds": self.max_seeds, "tolerance": self.tolerance}

    @classmethod
    def from_dict(cls, data: dict) -> "SequentialRule":
        return cls(int(data["min_seeds"]), int(data["max_seeds"]), float(data["tolerance"]))


def check_rule(table, where: str, pairs_per_seed: int) -> SequentialRule:
    """A plan's ``study.sequential`` table checked: known keys of the right types, 1 <= min_seeds <= max_seeds,
    tolerance in (0, 1), and at least 2 pairs at the first look (a t interval needs 2); else ValueError naming
    ``where`` and the key, in one line."""
    if not isinstance(table, dict):
        raise ValueError(f"{where}: expected a table {{min_seeds = 3, max_seeds = 8, tolerance = 0.01}}, got "
                         f"{table!r}")
    for key, value in table.items():
        if key not in SEQUENTIAL_KEYS:
            raise ValueError(f"{where}.{key}: unknown key; valid keys: {', '.join(SEQUENTIAL_KEYS)}")
        if isinstance(value, bool) or not isinstance(value, SEQUENTIAL_KEYS[key]):
            kind = "a number" if key == "tolerance" else "an integer"
            raise ValueError(f"{where}.{key}: expected {kind}, got {value!r}")
    for key in SEQUENTIAL_KEYS:
        if key not in table:
            raise ValueError(f"{where}.{key}: missing")
    rule = SequentialRule(table["min_seeds"], table["max_seeds"], float(table["tolerance"]))
    if not 1 <= rule.min_seeds <= rule.max_seeds:
        raise ValueError(f"{where}: expected 1 <= min_seeds <= max_seeds, got min_seeds = {rule.min_seeds}, "
                         f"max_seeds = {rule.max_seeds}")
    if rule.max_seeds > 50:
        raise ValueError(f"{where}.max_seeds: at most 50 seeds (looks), got {rule.max_seeds}")
    if not 0 < rule.tolerance < 1:
        raise ValueError(f"{where}.tolerance: expected a difference of mIoU in (0, 1), got {rule.tolerance}")
    if rule.looks(pairs_per_seed)[0] < 2:
        raise ValueError(f"{where}.min_seeds: the first look has {rule.looks(pairs_per_seed)[0]} pair (seeds x "
                         "folds); an interval needs 2, better 3 or more")
    return rule


def _null_statistics(looks: tuple[int, ...], replicates: int, seed: int) -> np.ndarray:
    """|t| [replicates, looks] of the paired t statistic at each look under the null (standard normal pairs),
    simulated through each look's group of new pairs: its sum ~ N(0, m) and its within-group sum of squares
    ~ chi2(m - 1), the sufficient statistics of m pairs."""
    generator = np.random.default_rng(seed)
    total = np.zeros(replicates)  # sum of the pairs so far
    squares = np.zeros(replicates)  # sum of their squares
    statistics = np.empty((replicates, len(looks)))
    previous = 0
    for index, n in enumerate(looks):
        m = n - previous
        group = generator.standard_normal(replicates) * math.sqrt(m)
        within = generator.chisquare(m - 1, replicates) if m > 1 else np.zeros(replicates)
        total += group
        squares += group ** 2 / m + within
        previous = n
        variance = np.maximum(squares - total ** 2 / n, 0.0) / (n - 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            statistics[:, index] = np.where(variance > 0, np.abs(total) / np.sqrt(n * variance), np.inf)
    return statistics


def crossing_probability(statistics: np.ndarray, looks: tuple[int, ...], nominal: float) -> float:
    """The share of null replicates (`_null_statistics`) whose |t| reaches t_{1-a'/2, n-1} at some look."""
    critical = np.array([critical_value(n, nominal) for n in looks])
    return float(np.mean((statistics >= critical).any(axis=1)))


@functools.lru_cache(maxsize=64)
def nominal_level(looks: tuple[int, ...], level: float = LEVEL, replicates: int = REPLICATES,
                  seed: int = CALIBRATION_SEED) -> float:
    """The two-sided nominal level a' of each look's t test such that, with the same camera twice, the paired t
    statistic crosses t_{1-a'/2, n-1} at some look of ``looks`` with probability 1 - ``level`` (Pocock-type).

    Args:
        looks: pairs at each planned look, increasing, the first >= 2.
        level: the confidence level (0.95: 5% false verdicts in all).
        replicates, seed: the calibration's null simulation.

    Returns:
        a' in (0, 1 - level]: the largest level whose simulated crossing probability is <= 1 - level less twice its
        Monte Carlo standard error (so that the true one is at most 1 - level: 0.0496 for 5% at 1,000,000
        replicates); bisection to 1e-7; 1 - level for a single look (exact).
    """
    looks = tuple(int(n) for n in looks)
    if not looks or looks[0] < 2 or any(b <= a for a, b in zip(looks, looks[1:])):
        raise ValueError(f"nominal_level: expected increasing looks of >= 2 pairs, got {looks}")
    alpha = 1 - level
    if len(looks) == 1:
        return alpha
    statistics = _null_statistics(looks, replicates, seed)
    target = alpha - 2 * math.sqrt(alpha * (1 - alpha) / replicates)
    low, high = alpha / len(looks) / 2, alpha  # Bonferroni's level (half of it) crosses less, alpha more
    while crossing_probability(statistics, looks, low) > target:
        low /= 2
    while high - low > 1e-7:
        middle = (low + high) / 2
        low, high = (middle, high) if crossing_probability(statistics, looks, middle) <= target else (low, middle)
    return low


def critical_value(n: int, nominal: float) -> float:
    """The t critical value of a look of ``n`` pairs at two-sided nominal level ``nominal``."""
    return float(stats.t.ppf(1 - nominal / 2, n - 1))


def repeated_interval(differences, nominal: float) -> dict:
    """The repeated confidence interval of a look: mean of the paired ``differences`` +- t_{1-a'/2, n-1} s / sqrt(n)
    at nominal level ``nominal`` (`nominal_level`). Returns {"mean", "low", "high", "n", "critical",
    "nominal_level"} (low = high = None for one pair)."""
    values = np.asarray(differences, dtype=np.float64)
    n = len(values)
    mean = float(values.mean())
    if n < 2:
        return {"mean": mean, "low": None, "high": None, "n": n, "critical": None, "nominal_level": nominal}
    critical = critical_value(n, nominal)
    half = critical * float(values.std(ddof=1)) / math.sqrt(n)
    return {"mean": mean, "low": mean - half, "high": mean + half, "n": n, "critical": critical,
            "nominal_level": nominal}


def verdict(intervals: list[dict | None]) -> str:
    """"better" / "worse" when every interval given (None: left out) excludes 0 on the same side, else not
    distinguishable (the report's rule, `warpsense.study.report._verdict`)."""
    intervals = [interval for interval in intervals if interval is not None]
    if intervals and all(distinguishable(interval) for interval in intervals):
        sides = {interval["low"] > 0 for interval in intervals}
        if len(sides) == 1:
            return "better" if sides.pop() else "worse"
    return NOT_DISTINGUISHABLE


def half_width(interval: dict) -> float | None:
    return None if interval["low"] is None else (interval["high"] - interval["low"]) / 2


STOPS = ("excludes_zero", "tolerance", "max_seeds")
"""Why a comparison stopped: its interval excludes 0, or holds 0 within the tolerance, or the last look."""


def judge(rule: SequentialRule, seeds: tuple, folds: tuple, values: dict, reference: dict,
          bootstrap: Callable[[list], dict | None] | None = None) -> dict:
    """Walk a comparison's looks in order and judge it where the sequential rule stops: at the first look whose
    repeated interval excludes 0, or holds 0 with a half-width <= the tolerance, or at max_seeds. The verdict there
    asks the bootstrap too (`verdict`), as the fixed rule does.

    Args:
        rule: the plan's rule.
        seeds: the plan's seeds in the order they are added (the first ``rule.max_seeds`` are used).
        folds: the plan's folds ("" alone without folds); each seed adds one pair per fold.
        values, reference: the camera's and the reference's score per (fold, seed).
        bootstrap: the bootstrap interval of the difference over a list of (fold, seed) keys (None: none), asked at
            the look where the comparison stops.

    Returns:
        {"state": "settled" or "unsettled", "stop": one of `STOPS` (settled), "look": the seeds of the look judged
        (the last complete one while unsettled; 0 before the first), "seeds": those seeds, "pairs", "paired": the
        look's repeated interval with "seeds" (its keys), "higher" and "lower" (sign counts), "bootstrap" (at the
        stop), "verdict", "needs_seeds": the seeds whose cells complete the next look (unsettled), "nominal_level",
        "looks" (pairs per planned look), "history": per complete look {seeds, pairs, mean, low, high},
        "tolerance", "min_seeds", "max_seeds"}.
    """
    looks = rule.looks(len(folds))
    nominal = nominal_level(looks, rule.level)
    common = set(values) & set(reference)
    history, judged = [], None
    result = {"nominal_level": nominal, "looks": list(looks), "tolerance": rule.tolerance,
              "min_seeds": rule.min_seeds, "max_seeds": rule.max_seeds}
    for index, count in enumerate(range(rule.min_seeds, rule.max_seeds + 1)):
        used = list(seeds[:count])
        keys = sorted(key for key in common if key[1] in used and key[0] in folds)
        if len(keys) < looks[index]:  # this look is not complete yet: its seeds' cells are needed
            return {**result, "state": "unsettled", "stop": None, "needs_seeds": used, "history": history,
                    **(judged or {"look": 0, "seeds": [], "pairs": 0, "paired": None}), "bootstrap": None,
                    "verdict": NOT_DISTINGUISHABLE}
        differences = [values[key] - reference[key] for key in keys]
        paired = {**repeated_interval(differences, nominal), "seeds": [list(key) for key in keys],
                  "higher": sum(d > 0 for d in differences), "lower": sum(d < 0 for d in differences)}
        judged = {"look": count, "seeds": used, "pairs": len(keys), "paired": paired}
        history.append({"seeds": count, "pairs": len(keys), "mean": paired["mean"], "low": paired["low"],
                        "high": paired["high"]})
        half = half_width(paired)
        stop = ("excludes_zero" if distinguishable(paired) else
                "tolerance" if half is not None and half <= rule.tolerance else
                "max_seeds" if count == rule.max_seeds else None)
        if stop is not None:
            boot = bootstrap(keys) if bootstrap is not None else None
            return {**result, **judged, "bootstrap": boot, "verdict": verdict([paired, boot]), "state": "settled",
                    "stop": stop, "needs_seeds": [], "history": history}
    raise AssertionError("unreachable: the last look stops")  # pragma: no cover


def stop_text(judgement: dict) -> str:
    """Where and why a comparison stopped, in words."""
    look = f"{judgement['look']} seed(s), {judgement['pairs']} pairs"
    if judgement["state"] == "unsettled":
        done = f"judged so far at {look}" if judgement["look"] else "no complete look yet"
        return f"unsettled ({done}): needs seed(s) {', '.join(map(str, judgement['needs_seeds']))}"
    why = {"excludes_zero": "the interval excludes 0",
           "tolerance": f"the interval holds 0 within +-{judgement['tolerance']:g}",
           "max_seeds": f"max_seeds ({judgement['max_seeds']})"}[judgement["stop"]]
    return f"stopped at {look}: {why}"

