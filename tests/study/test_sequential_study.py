"""A plan's study.sequential end to end: its keys and one-line errors, the rounds of seeds (only the unsettled
comparisons get another seed) checked by hand with a stand-in for training, the report judging each comparison where
it stopped, resuming after Ctrl-C, and the Slurm executor with --wait and without. tests/study/test_search.py trains
an adaptive study's rounds for real."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from tests.study.fakes import FakeTraining, fake_cluster
from warpsense.cli import main
from warpsense.resources import CONFIG_DIR
from warpsense.study import load_plan, study_record, training
from warpsense.study.plan import Plan
from warpsense.study.report import render_text
from warpsense.study.sequential import critical_value, nominal_level

SEQUENTIAL = "sequential = {min_seeds = 2, max_seeds = 5, tolerance = 0.004}\n"
CAMERAS = '''
[[camera]]
name = "far"                  # a clearly better camera (the stand-in scores it +0.05)
set = ["cfa.mode=\\"fixed\\"", "cfa.pattern=\\"RCCB\\"", "exposure.learnable=false"]

[[camera]]
name = "twin"                 # the reference again, with its own seeds: an A/A comparison
set = ["cfa.mode=\\"fixed\\"", "exposure.learnable=false"]
seed_offset = 100
'''
NOISE = {0: 0.010, 1: -0.012, 2: 0.003, 3: -0.002, 4: 0.001, 100: -0.011, 101: 0.009, 102: -0.004, 103: 0.003,
         104: 0.0}
"""The stand-in's seed noise of each run.seed (the twin's seeds are 100 + the cell's)."""


def _plan_file(tmp_path: Path, study: str = SEQUENTIAL, cameras: str = CAMERAS) -> Path:
    text = (CONFIG_DIR / "studies" / "smoke.toml").read_text()
    text = text.replace('reference = "rggb"\n', f'reference = "rggb"\n{study}')
    start = text.index("[[camera]]\nname = \"rccb\"")
    end = text.index("[[light]]")
    path = tmp_path / "plan.toml"
    path.write_text(text[:start] + cameras.lstrip() + "\n" + text[end:])
    return path


def _score(config, cell) -> float:
    return 0.40 + (0.05 if cell.camera == "far" else 0.0) + NOISE[config.run.seed]


def test_the_plan_extends_its_seeds_and_refuses_bad_rules(tmp_path, capsys):
    plan = load_plan(_plan_file(tmp_path))
    assert plan.seeds == (0, 1, 2, 3, 4) and plan.sequential.to_dict() == {"min_seeds": 2, "max_seeds": 5,
                                                                           "tolerance": 0.004}
    assert Plan.from_dict(json.loads(json.dumps(plan.to_dict()))) == plan
    assert "sequential" not in load_plan("smoke").to_dict()
    out = tmp_path / "study"
    assert main(["study", "run", str(_plan_file(tmp_path)), "--out", str(out), "--plan-only"]) == 0
    printed = capsys.readouterr().out
    assert "# study.sequential: every cell's first 2 seed(s) are needed; seeds 2, 3, 4 only for comparisons still " \
           "unsettled" in printed and printed.count("--cell") == 15 and not out.exists()
    for study, message, seeds in (
            ("sequential = {min_seeds = 2, max_seeds = 5}\n", "study.sequential.tolerance: missing", None),
            ("sequential = {min_seeds = 2, max_seeds = 5, tolerance = 0.01, level = 0.9}\n",
             "study.sequential.level: unknown key; valid keys: min_seeds, max_seeds, tolerance", None),
            ("sequential = {min_seeds = 1, max_seeds = 5, tolerance = 0.01}\n", "the first look has 1 pair", None),
            ("sequential = 3\n", "study.sequential: expected dict", None),
            ("sequential = {min_seeds = 2, max_seeds = 2, tolerance = 0.01}\n",
             "study.seeds: 3 seeds listed, study.sequential.max_seeds is 2", "seeds = [0, 1, 2]")):
        plan_file = _plan_file(tmp_path, study)
        if seeds:
            plan_file.write_text(plan_file.read_text().replace("seeds = [0, 1]", seeds))
        assert main(["study", "run", str(plan_file), "--out", str(out)]) == 2
        error = capsys.readouterr().err.strip()
        assert len(error.splitlines()) == 1 and message in error, error
        assert not out.exists()
    # with block folds a seed adds a pair per fold: the first look's pairs count the folds
    folds = load_plan(_plan_file(tmp_path, "sequential = {min_seeds = 1, max_seeds = 3, tolerance = 0.01}\n"
                                           "folds = \"blocks\"\nblocks = 3\nblock_buffer = 0\n"),
                      ["data.scenes_train=40"])
    assert folds.sequential.looks(len(folds.fold_names())) == (3, 6, 9)


def _by_hand(values: list[float], looks: tuple[int, ...]) -> tuple[float, float]:
    nominal = nominal_level(looks)
    half = critical_value(len(values), nominal) * np.std(values, ddof=1) / np.sqrt(len(values))
    return np.mean(values) - half, np.mean(values) + half


def test_only_unsettled_comparisons_get_more_seeds_and_the_report_judges_where_they_stopped(tmp_path, monkeypatch,
                                                                                           capsys):
    fake = FakeTraining(_score)
    monkeypatch.setattr(training, "train_cell", fake)
    out = tmp_path / "study"
    assert main(["study", "run", str(_plan_file(tmp_path)), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    looks = (2, 3, 4, 5)
    # seeds 0, 1 of every camera; "far" stops there (its interval excludes 0); the twin goes on until its interval
    # holds 0 within +-0.004 (by hand below), the reference with it
    twin_differences = [NOISE[100 + s] - NOISE[s] for s in range(5)]
    stop = next(k for k in looks if (lambda low, high: low > 0 or high < 0 or (high - low) / 2 <= 0.004)(
        *_by_hand(twin_differences[:k], looks)) or k == 5)
    assert 2 < stop <= 5
    expected = [f"{camera}/night/{s}" for s in (0, 1) for camera in ("rggb", "far", "twin")]
    expected += [f"{camera}/night/{s}" for s in range(2, stop) for camera in ("rggb", "twin")]
    assert fake.trained == expected
    assert "study: sequential: 1 comparison(s) unsettled (twin at night: unsettled (judged so far at 2 seed(s), 2 " \
           "pairs): needs seed(s) 0, 1, 2)" in printed
    record = study_record(out, resamples=50)
    assert record["missing"] == []  # seeds past a comparison's stop are not missing
    assert main(["study", "status", str(out)]) == 0  # ... nor pending
    assert f"{len(expected)} cells: {len(expected)} done, 0 running, 0 pending" in capsys.readouterr().out
    far, twin = record["splits"]["val"]["comparisons"]
    assert far["camera"] == "far" and far["verdict"] == "better"
    assert far["sequential"]["stop"] == "excludes_zero" and far["sequential"]["look"] == 2
    assert far["paired"]["n"] == 2 and far["paired"]["mean"] == pytest.approx(0.05)
    assert twin["verdict"] == "not distinguishable" and twin["sequential"]["look"] == stop
    assert (twin["paired"]["low"], twin["paired"]["high"]) == pytest.approx(_by_hand(twin_differences[:stop], looks))
    assert twin["paired"]["nominal_level"] == pytest.approx(nominal_level(looks))
    # wider than the fixed 95% interval over the same pairs: the price of looking four times
    fixed = stats.t.ppf(0.975, stop - 1) * np.std(twin_differences[:stop], ddof=1) / np.sqrt(stop)
    assert (twin["paired"]["high"] - twin["paired"]["low"]) / 2 > fixed
    assert [h["seeds"] for h in twin["sequential"]["history"]] == list(range(2, stop + 1))
    text = render_text(record)
    assert "[val] sequential verdicts: 2..5 seeds, another seed while the interval holds 0 and is wider than +-0.004" \
        in text and f"twin  stopped at {stop} seed(s), {stop} pairs" in text
    assert "far   stopped at 2 seed(s), 2 pairs: the interval excludes 0" in text

    # the same study stopped by Ctrl-C in its 8th cell and run again: the same cells, none trained twice
    interrupted = FakeTraining(_score, stop_after=7)
    monkeypatch.setattr(training, "train_cell", interrupted)
    again = tmp_path / "again"
    assert main(["study", "run", str(_plan_file(tmp_path)), "--out", str(again)]) == 130
    rest = FakeTraining(_score)
    monkeypatch.setattr(training, "train_cell", rest)
    assert main(["study", "run", str(_plan_file(tmp_path)), "--out", str(again)]) == 0
    assert interrupted.trained + rest.trained == expected


def test_slurm_rounds_with_and_without_wait(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(training, "train_cell", FakeTraining(_score))
    arrays = []
    fake_cluster(monkeypatch, arrays)
    plan = str(_plan_file(tmp_path))
    waited = tmp_path / "waited"
    assert main(["study", "run", plan, "--out", str(waited), "--executor", "slurm", "--wait"]) == 0
    rounds = [list(cells) for cells in arrays]
    assert rounds[0] == [f"{c}/night/{s}" for s in (0, 1) for c in ("rggb", "far", "twin")]
    assert all(cells == [f"rggb/night/{k}", f"twin/night/{k}"] for k, cells in enumerate(rounds[1:], start=2))
    arrays.clear()
    capsys.readouterr()
    stepwise = tmp_path / "stepwise"  # without --wait: one round a call; each call goes on from the directory
    calls = 0
    while True:
        assert main(["study", "run", plan, "--out", str(stepwise), "--executor", "slurm"]) == 0
        calls += 1
        if "every comparison has stopped" in capsys.readouterr().out:
            break
        assert calls < 10
    assert arrays == rounds and calls == len(rounds) + 1
