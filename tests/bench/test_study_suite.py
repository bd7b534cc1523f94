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


BROKEN_FIRST = '''[study]
name = "broken_first"
base = ""
set = ["data.scenes_train=16", "data.scenes_val=4", "data.scene_height=32", "data.scene_width=48",
       "data.crop_height=32", "data.crop_width=48", "data.batch_size=4", "model.width=4", "train.epochs=2",
       "train.warmup_epochs=1", "train.eval_every=2", "train.plots=false", "run.device=\\"cpu\\""]
seeds = [0]
reference = "rggb"

[[camera]]
name = "broken"               # the fixed ISP cannot demosaic clear pixels: fails when the cell builds its model
set = ["cfa.mode=\\"fixed\\"", "cfa.pattern=\\"RCCB\\"", "isp.enabled=true"]

[[camera]]
name = "rggb"
set = ["cfa.mode=\\"fixed\\"", "exposure.learnable=false"]

[[light]]
name = "night"
full_well_electrons = 66.66666666666667
read_electrons = 0.13333333333333333
bits = 10
'''


def _suite_command(plan, out, cells: int = 2) -> list[str]:
    return ["bench", "--suite", "study", "--plan", str(plan), "--out", str(out), "--cells", str(cells), "--gpus",
            "none"]


def test_a_failed_cell_stops_the_suite_before_its_second_invocation(tmp_path, capsys, monkeypatch):
    """A cell failed in the alone invocation: the shared one trained every cell again (and failed the same way),
    then a RuntimeError's traceback ended the command. Now, as `study run`: the other cells of that invocation
    go on, the suite stops there, and says so in one line (exit 1)."""
    from warpsense.cli import main
    from warpsense.study import runner

    plan = tmp_path / "plan.toml"
    plan.write_text(BROKEN_FIRST)
    out = tmp_path / "suite"
    invocations = []
    real = runner.run_cells
    monkeypatch.setattr("warpsense.bench.study_suite.run_cells",
                        lambda plan, folder, *args, **kwargs: invocations.append(folder.name) or real(
                            plan, folder, *args, **kwargs))
    assert main(_suite_command(plan, out)) == 1
    error = capsys.readouterr().err
    assert invocations == ["alone"] and not (out / "shared").exists()
    assert (out / "alone" / "runs" / "rggb.night.seed0" / "evaluation.json").is_file()  # the other cell went on
    last = error.strip().splitlines()[-1]
    assert last.startswith("warpsense bench: study suite: cells failed in the alone invocation")
    assert "stopped before the shared invocation" in last and "Traceback" not in error


@pytest.mark.parametrize("signal_name", ["SIGINT", "SIGTERM"])
def test_ctrl_c_or_sigterm_stops_the_suite_at_once_and_it_resumes(tmp_path, capsys, monkeypatch, signal_name,
                                                                   ctrl_c):
    """Ctrl-C (or SIGTERM) in the alone invocation's first cell: the alone invocation stopped that cell, and then
    the shared invocation started training all cells anew. Now the suite stops there (exit 130, 143 for SIGTERM),
    one line, no traceback, and the same command resumes the interrupted cell and finishes."""
    import os
    import signal

    from warpsense.cli import main
    from warpsense.train import engine

    plan = tmp_path / "plan.toml"
    plan.write_text(BROKEN_FIRST.replace('name = "broken"', 'name = "rccb"').replace(
        '"cfa.pattern=\\"RCCB\\"", "isp.enabled=true"', '"cfa.pattern=\\"RCCB\\""'))
    out = tmp_path / "suite"
    write_epoch = engine._write_epoch

    def interrupted(run_dir, *args, **kwargs):
        write_epoch(run_dir, *args, **kwargs)
        os.kill(os.getpid(), getattr(signal, signal_name))  # after the first epoch's checkpoint

    monkeypatch.setattr(engine, "_write_epoch", interrupted)
    assert main(_suite_command(plan, out, cells=1)) == (130 if signal_name == "SIGINT" else 143)
    error = capsys.readouterr().err
    assert "Traceback" not in error and not (out / "shared").exists()
    assert error.strip().splitlines()[-1] == (f"warpsense bench: study suite: interrupted in the alone invocation "
                                              f"({out / 'alone'}) before the shared invocation; run the same command "
                                              "again to resume (finished cells are kept)")
    assert (out / "alone" / "runs" / "rccb.night.seed0" / "checkpoint_last.safetensors").is_file()
    monkeypatch.setattr(engine, "_write_epoch", write_epoch)
    assert main(_suite_command(plan, out, cells=1)) == 0
    assert "resuming" in capsys.readouterr().out
    records = [json.loads(line) for line in
               (out / "alone" / "runs" / "rccb.night.seed0" / "metrics.jsonl").read_text().splitlines()]
    assert [record["epoch"] for record in records] == [0, 1]  # epoch 1 trained once, after the resume


def test_a_damaged_evaluation_of_the_suite_is_named(tmp_path):
    from warpsense.study.plan import PlanError

    with pytest.raises(PlanError, match=r"run/evaluation.json: splits.val.miou: expected a finite score"):
        judged_miou({"splits": {"val": {"miou": float("nan")}}}, "run/evaluation.json")
    with pytest.raises(PlanError, match=r"run/evaluation.json: splits: expected an object"):
        judged_miou({}, "run/evaluation.json")
