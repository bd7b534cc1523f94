import json

import pytest

from tests.train.test_training import TINY
from warpsense.config import load_config
from warpsense.system.checkpoint import read_checkpoint
from warpsense.train.engine import LAST, train
from warpsense.train.schedule import Schedule


def test_phases_follow_the_plan():
    schedule = Schedule(epochs=6, warmup_epochs=2)
    assert [schedule.phase(e) for e in range(6)] == ["warmup"] * 2 + ["joint"] * 4
    assert [schedule.is_joint(e) for e in range(6)] == [False] * 2 + [True] * 4


@pytest.mark.parametrize("plan, epochs, expected", [
    ((100, 4), 10, (10, 1)), ((100, 40), 10, (10, 4)), ((10, 0), 5, (5, 0)), ((10, 10), 4, (4, 4)),
    ((10, 9), 2, (2, 1)), ((10, 3), 10, (10, 3)), ((10, 3), 20, (10, 3))])
def test_shortening_keeps_the_phases_the_plan_has(plan, epochs, expected):
    shortened = Schedule(*plan).shortened(epochs)
    assert (shortened.epochs, shortened.warmup_epochs) == expected


def test_epochs_within_a_budget():
    schedule = Schedule(100, 4)
    assert schedule.epochs_within(111.0, 1.0) == 100  # everything fits
    assert schedule.epochs_within(56.0, 1.0) == 50  # an epoch plus 10% for evaluation
    assert schedule.epochs_within(1.0, 1.0) == 2  # never below two epochs


def test_time_budget_shortens_the_run_not_its_config_and_resume_keeps_the_shortened_plan(tmp_path, capsys):
    config = load_config(None, TINY + ["train.epochs=5", "train.warmup_epochs=2", "train.time_budget_minutes=1e-6",
                                       f"run.output_dir={tmp_path}"])
    run = train(config, progress=False)
    warning = [line for line in capsys.readouterr().err.splitlines() if "cannot be met" in line]
    assert len(warning) == 1 and "the shortest plan (2 epochs) needs about" in warning[0]
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["phase"] for r in records] == ["warmup", "joint"]  # 5 epochs (2 warm-up) cut to 2 (1 warm-up)
    assert config.train.epochs == 5 and config.train.warmup_epochs == 2  # the caller's config is untouched
    assert json.loads((run / "config.json").read_text())["train"]["epochs"] == 5  # the run's request, as given
    state = read_checkpoint(run / LAST)[1]["state"]
    assert state["schedule"] == {"epochs": 2, "warmup_epochs": 1, "requested": [5, 2]}
    train(config, resume=run, progress=False)  # the same request: the run is complete under its shortened plan
    assert len((run / "metrics.jsonl").read_text().splitlines()) == 2


def test_a_resumed_run_takes_the_saved_plan_only_for_the_same_request_and_checks_it():
    from pathlib import Path

    from warpsense.system.checkpoint import CheckpointError
    from warpsense.train.engine import _resumed_schedule

    requested = Schedule.from_config(load_config(None, ["train.epochs=10", "train.warmup_epochs=4"]).train)
    saved = {"epochs": 6, "warmup_epochs": 2, "requested": [10, 4]}
    checkpoint = Path("run/checkpoint_last.safetensors")
    assert _resumed_schedule({"schedule": saved}, requested, checkpoint) == Schedule(6, 2)
    assert _resumed_schedule({}, requested, checkpoint) == Schedule(10, 4)  # written before schedules were saved
    changed = load_config(None, ["train.epochs=20", "train.warmup_epochs=4"])  # --allow-config-change
    assert _resumed_schedule({"schedule": saved}, Schedule.from_config(changed.train), checkpoint) == Schedule(20, 4)
    with pytest.raises(CheckpointError, match="checkpoint_last.safetensors: state.schedule"):
        _resumed_schedule({"schedule": {**saved, "warmup_epochs": 7}}, requested, checkpoint)
