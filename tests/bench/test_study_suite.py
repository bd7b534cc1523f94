"""The study suite: the same cells one per GPU and several per GPU, their scores and times side by side."""

import json

import pytest

from warpsense.bench.study_suite import format_study_suite, judged_miou, run_study_suite

SMALL = ("train.epochs=2", "train.warmup_epochs=1", "data.scenes_train=16", "data.scenes_val=4",
         "data.batch_size=4", "train.eval_every=2")


def test_feature_cells_repeat_and_the_record_compares_them(tmp_path):
    """On a CPU both invocations run the cells in this process: each cell repeats exactly (difference 0), and the
    record carries per-cell times, the invocations' throughput and their ratio."""
    record = run_study_suite("smoke", tmp_path / "suite", cells=2, per_gpu=2, overrides=SMALL)
    assert [row["cell"] for row in record["cells"]] == ["rggb/night/0", "rccb/night/0"]
    for row in record["cells"]:
        assert row["split"] == "val" and 0.0 <= row["alone"]["miou"] <= 1.0
        assert row["miou_difference"] == 0.0  # CPU runs repeat bitwise
        for side in ("alone", "shared"):
            assert row[side]["steady_s"] > 0 and row[side]["wall_s"] > 0
        assert row["speedup"] == pytest.approx(row["alone"]["steady_s"] / row["shared"]["steady_s"])  # one process
    assert record["per_gpu"] == 1 and record["gpus"] == [] and record["alone"]["cells_finished"] == 2
    assert record["ratio"] == pytest.approx(record["cells_per_gpu_hour"]["shared"]
                                            / record["cells_per_gpu_hour"]["alone"])
    assert record["steady_ratio"] == pytest.approx(sum(row["alone"]["steady_s"] for row in record["cells"])
                                                   / sum(row["shared"]["steady_s"] for row in record["cells"]))
    text = format_study_suite(record)
    assert "rggb/night/0" in text and "cells per GPU-hour" in text
    again = run_study_suite("smoke", tmp_path / "suite", cells=2, per_gpu=2, overrides=SMALL)  # finished: kept
    assert [row["alone"]["miou"] for row in again["cells"]] == [row["alone"]["miou"] for row in record["cells"]]


def test_feature_a_fresh_workers_first_use_is_left_out_of_a_cells_time(tmp_path):
    """A cell that came first on a pool worker paid the process's first use (Warp's kernels compiled: a 20 s first
    epoch); its steady time counts that epoch at the median of the others, so it compares with a warm cell."""
    from warpsense.bench.study_suite import _cell_times

    records = [{"epoch": 0, "phase": "warmup", "train_loss": 1.0, "setup_s": 1.0, "epoch_time_s": 20.0, "wall_s": 21.0},
               {"epoch": 1, "phase": "joint", "train_loss": 1.0, "epoch_time_s": 1.0, "wall_s": 22.0},
               {"epoch": 2, "phase": "joint", "train_loss": 1.0, "epoch_time_s": 1.5, "wall_s": 23.5}]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(record) + "\n" for record in records))
    times = _cell_times(tmp_path)
    # by hand: setup 1 + the first epoch at the median of the others' shares (1.0, 1.5) + 1.0 + 1.5
    assert times == {"wall_s": 23.5, "steady_s": pytest.approx(1.0 + 1.25 + 1.0 + 1.5), "epoch_s": 1.25}


def test_exception_per_gpu_below_two(tmp_path):
    with pytest.raises(ValueError, match="--per-gpu must be >= 2"):
        run_study_suite("smoke", tmp_path, per_gpu=1)


def test_judged_split_is_the_held_out_sequence_when_there_is_one():
    assert judged_miou({"splits": {"val": {"miou": 0.5}, "heldout": {"miou": 0.4}}}) == ("heldout", 0.4)
    assert judged_miou({"splits": {"val": {"miou": 0.5}}}) == ("val", 0.5)


def test_cli_runs_the_suite_and_writes_its_record(tmp_path, capsys):
    import json

    from warpsense.cli import main

    args = ["bench", "--suite", "study", "--plan", "smoke", "--out", str(tmp_path / "suite"), "--cells", "1",
            "--gpus", "none", "--json", str(tmp_path / "study.json")]
    for override in SMALL:
        args += ["--set", override]
    assert main(args) == 0
    record = json.loads((tmp_path / "study.json").read_text())
    assert record["suite"] == "study" and [row["cell"] for row in record["cells"]] == ["rggb/night/0"]
    assert "cells per GPU-hour" in capsys.readouterr().out


@pytest.mark.parametrize("args,message", [
    (["--suite", "kernels", "--plan", "smoke"], "--plan: options of the study suite"),
    (["--suite", "train", "--per-gpu", "3", "--set", "train.epochs=1"], "--per-gpu: options of the study"),
    (["--suite", "kernels", "--set", "model.squeeze=true"], "--set configures the train and study suites, not "
                                                            "--suite kernels"),
    (["--suite", "train", "--set", "model.sqeeze=true"], "model.sqeeze"),
    (["--suite", "study", "--plan", "smoke"], "needs --plan"),
])
def test_exception_cli_options(args, message, capsys):
    from warpsense.cli import main

    assert main(["bench", *args]) != 0
    assert message in capsys.readouterr().err
