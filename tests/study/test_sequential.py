"""Sequential verdicts (warpsense.study.sequential) against independent references: the single t test, Pocock's
published constants, a multivariate normal integral of the boundary-crossing probability, a Monte Carlo of raw
Gaussian pairs, and comparisons walked look by look by hand; the A/A simulation (warpsense.study.false_verdicts)
against Armitage et al.'s repeated-significance rates."""

import math

import numpy as np
import pytest
from scipy import stats

from warpsense.study.false_verdicts import (
    normal_differences,
    resampled_by_fold,
    resampled_differences,
    seed_residuals,
    simulate,
)
from warpsense.study.sequential import (
    SequentialRule,
    check_rule,
    critical_value,
    judge,
    nominal_level,
    repeated_interval,
)

POCOCK = {2: 2.178, 3: 2.289, 5: 2.413}
"""Pocock's (1977, Biometrika 64, Table 1) constant boundary for K equally spaced looks, two-sided 5%, known
variance (also Jennison and Turnbull 2000, Table 2.1)."""

ARMITAGE = {2: 0.083, 3: 0.107, 5: 0.142}
"""Armitage, McPherson and Rowe (1969): the chance that a 5% two-sided test repeated at K equally spaced looks
rejects a true null at some look (Jennison and Turnbull 2000, Table 1.1)."""


def test_a_single_look_is_the_fixed_t_test():
    assert nominal_level((15,)) == pytest.approx(0.05)
    assert critical_value(15, 0.05) == pytest.approx(stats.t.ppf(0.975, 14))


@pytest.mark.parametrize("looks", [2, 3, 5])
def test_many_pairs_per_look_give_pococks_constant(looks):
    """With 200 pairs a look the t statistics are normal ones: the nominal level's normal quantile is Pocock's."""
    nominal = nominal_level(tuple(200 * k for k in range(1, looks + 1)))
    assert stats.norm.isf(nominal / 2) == pytest.approx(POCOCK[looks], abs=0.012)


def test_crossing_probability_by_a_multivariate_normal_integral():
    """The boundary found for 4 looks of 300, 600, 900 and 1500 pairs (unequal increments), as a normal boundary:
    1 - P(all |Z_k| < c) with corr(Z_i, Z_j) = sqrt(n_i / n_j), integrated by Genz's method, is 5%."""
    looks = (300, 600, 900, 1500)
    c = stats.norm.isf(nominal_level(looks) / 2)
    n = np.array(looks, dtype=float)
    correlation = np.sqrt(np.minimum.outer(n, n) / np.maximum.outer(n, n))
    inside = stats.multivariate_normal(mean=np.zeros(4), cov=correlation).cdf(
        np.full(4, c), lower_limit=np.full(4, -c), rng=np.random.default_rng(0))
    assert 1 - inside == pytest.approx(0.0496, abs=0.002)  # 5% less twice the calibration's standard error


def test_few_pairs_per_look_keep_five_percent_on_raw_gaussian_pairs():
    """No folds, 3..8 seeds: 6 looks of 3..8 pairs (t with 2..7 degrees of freedom). Raw standard normal pairs (not
    the calibration's sufficient statistics), each look's t statistic from numpy: 5% cross at some look, where the
    fixed 95% t interval looked at every seed crosses far more often."""
    looks = tuple(range(3, 9))
    nominal = nominal_level(looks)
    pairs = np.random.default_rng(123).standard_normal((60_000, 8))
    crossed = np.zeros(len(pairs), dtype=bool)
    peeked = np.zeros(len(pairs), dtype=bool)
    for n in looks:
        head = pairs[:, :n]
        t = np.abs(head.mean(1)) / (head.std(1, ddof=1) / math.sqrt(n))
        crossed |= t >= critical_value(n, nominal)
        peeked |= t >= stats.t.ppf(0.975, n - 1)
    assert crossed.mean() == pytest.approx(0.05, abs=3 * math.sqrt(0.05 * 0.95 / len(pairs)))
    assert peeked.mean() > 0.10


def test_repeated_interval_by_hand():
    differences = [0.01, 0.03, 0.02, 0.04]
    interval = repeated_interval(differences, 0.01)
    half = stats.t.ppf(0.995, 3) * np.std(differences, ddof=1) / 2
    assert interval["mean"] == pytest.approx(0.025)
    assert (interval["low"], interval["high"]) == pytest.approx((0.025 - half, 0.025 + half))
    assert repeated_interval([0.1], 0.01)["low"] is None


def _scores(differences: dict) -> tuple[dict, dict]:
    """Camera and reference scores per (fold, seed) whose differences are ``differences``."""
    reference = {key: 0.5 for key in differences}
    return {key: 0.5 + d for key, d in differences.items()}, reference


FOLDS = ("b1", "b2", "b3")
SEEDS = (0, 1, 2, 3, 4)


def test_judge_stops_at_the_first_look_with_a_clear_verdict():
    rule = SequentialRule(2, 5, 0.001)
    values, reference = _scores({(f, s): 0.05 + 0.001 * i for i, (f, s) in enumerate(
        (f, s) for f in FOLDS for s in SEEDS[:2])})
    result = judge(rule, SEEDS, FOLDS, values, reference)
    assert result["state"] == "settled" and result["stop"] == "excludes_zero" and result["verdict"] == "better"
    assert result["look"] == 2 and result["pairs"] == 6 and result["needs_seeds"] == []
    nominal = nominal_level((6, 9, 12, 15))
    assert result["nominal_level"] == nominal
    assert result["paired"]["high"] - result["paired"]["mean"] == pytest.approx(
        critical_value(6, nominal) * np.std([0.05 + 0.001 * i for i in range(6)], ddof=1) / math.sqrt(6))


def test_judge_needs_the_next_seed_then_settles_within_the_tolerance():
    rule = SequentialRule(2, 5, 0.01)
    noisy = {(f, s): d for (f, s), d in zip(((f, s) for s in SEEDS for f in FOLDS),
                                           [0.03, -0.02, 0.01, -0.03, 0.02, -0.01, 0.004, -0.004, 0.0, 0.001, -0.001,
                                            0.002, 0.0, 0.001, -0.002])}
    first = {key: d for key, d in noisy.items() if key[1] in (0, 1)}
    result = judge(rule, SEEDS, FOLDS, *_scores(first))
    assert result["state"] == "unsettled" and result["needs_seeds"] == [0, 1, 2] and result["look"] == 2
    assert result["verdict"] == "not distinguishable" and len(result["history"]) == 1
    result = judge(rule, SEEDS, FOLDS, *_scores(noisy))
    assert result["state"] == "settled" and result["stop"] == "tolerance"
    assert result["paired"]["low"] < 0 < result["paired"]["high"]
    assert (result["paired"]["high"] - result["paired"]["low"]) / 2 <= 0.01
    # looks before the stop were wider than the tolerance: that is why it went on
    assert all((look["high"] - look["low"]) / 2 > 0.01 for look in result["history"][:-1])


def test_judge_stops_at_max_seeds_and_ignores_seeds_past_the_stop():
    rule = SequentialRule(1, 2, 1e-6)
    differences = {(f, s): (-1) ** (i + s) * 0.02 for i, f in enumerate(FOLDS) for s in SEEDS}
    result = judge(rule, SEEDS, FOLDS, *_scores(differences))
    assert result["stop"] == "max_seeds" and result["look"] == 2 and result["pairs"] == 6
    assert sorted({tuple(key)[1] for key in result["paired"]["seeds"]}) == [0, 1]
    empty = judge(rule, SEEDS, FOLDS, {}, {})
    assert empty["state"] == "unsettled" and empty["look"] == 0 and empty["needs_seeds"] == [0]


def test_judge_asks_the_bootstrap_at_the_stop_and_needs_both_intervals():
    rule = SequentialRule(1, 3, 1e-6)
    differences = {(f, s): 0.05 + 0.001 * s + 0.002 * i for i, f in enumerate(FOLDS) for s in SEEDS}
    asked = []

    def wide(keys):
        asked.append(keys)
        return {"mean": 0.05, "low": -0.01, "high": 0.11}

    result = judge(rule, SEEDS, FOLDS, *_scores(differences), bootstrap=wide)
    # the paired interval excludes 0 at the first look: it stops there, but the bootstrap holds 0: no verdict
    assert result["stop"] == "excludes_zero" and result["look"] == 1
    assert result["verdict"] == "not distinguishable" and result["bootstrap"]["low"] == -0.01
    assert asked == [[("b1", 0), ("b2", 0), ("b3", 0)]]


@pytest.mark.parametrize(("table", "message"), [
    ({"min_seeds": 3, "max_seeds": 8}, "sequential.tolerance: missing"),
    ({"min_seeds": 3, "max_seeds": 8, "tolerance": 0.01, "alpha": 0.1}, "sequential.alpha: unknown key"),
    ({"min_seeds": 4, "max_seeds": 3, "tolerance": 0.01}, "expected 1 <= min_seeds <= max_seeds"),
    ({"min_seeds": 1, "max_seeds": 3, "tolerance": 0.01}, "the first look has 1 pair"),
    ({"min_seeds": 3, "max_seeds": 8, "tolerance": 2}, "tolerance: expected a difference of mIoU in (0, 1)"),
    ({"min_seeds": 3.0, "max_seeds": 8, "tolerance": 0.01}, "min_seeds: expected an integer"),
])
def test_bad_rules_are_one_line_errors(table, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        check_rule(table, "plan.toml: study.sequential", 1)


def test_armitage_repeated_significance_and_the_sequential_rule_in_the_simulation():
    """Normal A/A pairs, 50 a look, 1..K looks: the fixed interval looked at every look calls Armitage et al.'s
    share; the fixed rule at any one look 5%; the sequential rule 5% in all (no tolerance stops)."""
    for looks in (2, 3, 5):
        result = simulate(normal_differences(0.01), 50, SequentialRule(1, looks, 1e-9), replicates=20_000, seed=7)
        tolerance = 3 * math.sqrt(0.05 * 0.95 / 20_000)
        assert result["peeking"][-1]["cumulative"] == pytest.approx(ARMITAGE[looks], abs=0.008)
        assert all(row["rate"] == pytest.approx(0.05, abs=tolerance) for row in result["fixed"])
        assert result["overall"] == pytest.approx(0.05, abs=tolerance) == result["any_look"]


def test_simulation_counts_stopping_times_and_tolerance_stops_lower_the_rate():
    rule = SequentialRule(3, 8, 0.01)
    result = simulate(normal_differences(0.015), 5, rule, replicates=20_000, seed=3)
    stops = result["sequential"]
    assert [row["seeds"] for row in stops] == list(range(3, 9))
    assert sum(row["stopped"] for row in stops) == pytest.approx(1.0)
    assert stops[-1]["cumulative"] == pytest.approx(result["overall"]) and result["overall"] <= 0.05
    assert all(row["false"] <= row["stopped"] for row in stops)
    assert 3 <= result["mean_seeds"] < 8
    # sd 0.015: an A/A pair's difference has sd 0.0212; the expected half-width 2.72 x 0.0212 / sqrt(15) = 0.0149 at
    # 3 seeds, 0.0109 at 5, 0.0098 at 6: few comparisons stop on the tolerance before 5 seeds, most at 5-7
    assert stops[0]["stopped"] < 0.1 and stops[2]["stopped"] + stops[3]["stopped"] + stops[4]["stopped"] > 0.6


def test_seed_residuals_and_resampling_from_rows():
    rows = [{"archive": "a.tar.xz", "directory": "s", "plan": "p", "camera": camera, "light": "night", "fold": fold,
             "seed": seed, "miou": value}
            for camera, fold, values in (("x", "f1", [0.40, 0.42, 0.44]), ("y", "f1", [0.30, 0.31, 0.35]),
                                         ("x", "f2", [0.50, 0.50]), ("y", "f2", [0.2]))
            for seed, value in enumerate(values)]
    measured = seed_residuals(rows)
    squares = 0.02 ** 2 * 2 + (0.01 ** 2 + 0.02 ** 2 + 0.03 ** 2) + 0.0  # centred sums of squares by hand
    assert measured["sd"] == pytest.approx(math.sqrt(squares / 5))
    assert measured["groups"] == 3 and measured["runs"] == 8
    assert measured["residuals"][:3] == pytest.approx(np.array([-0.02, 0.0, 0.02]) * math.sqrt(1.5))
    differences = np.array([0.10, 0.11, 0.09])  # x - y at f1, seeds 0..2 (f2 has one common seed)
    assert measured["paired_sd"] == pytest.approx(np.std(differences, ddof=1))
    draws = resampled_differences(measured["residuals"])(np.random.default_rng(0), (1000, 2, 3))
    assert draws.shape == (1000, 2, 3) and abs(draws.mean()) < 0.005
    by_fold = resampled_by_fold(measured["by_fold"])(np.random.default_rng(0), (500, 2, 2))
    assert np.all(by_fold[..., 1] == 0.0)  # f2's only residuals are 0 (two equal runs)
    with pytest.raises(ValueError, match="2 folds' residuals, asked for 3 folds"):
        resampled_by_fold(measured["by_fold"])(np.random.default_rng(0), (5, 2, 3))
