"""Run directories (issue 14, items 2, 9, 10): which run --resume means, the config a resumed run keeps, a torn
metrics line, the run lock, and Ctrl-C."""

import json
import os
import socket
import subprocess
import sys

import pytest

from tests.train.test_training import TINY
from warpsense.cli import main
from warpsense.config import ConfigError, load_config
from warpsense.train import engine
from warpsense.train.run_dir import LAST, RunDir, RunLock, newest_run, read_metrics, resumed_config


def _run(tmp_path, name="tiny", extra=()):
    config = load_config(None, TINY + ["train.epochs=1", "train.warmup_epochs=0", f"run.output_dir={tmp_path}",
                                       f"run.name={name}", *extra])
    return config, engine.train(config, progress=False)


def test_newest_run_is_the_highest_suffix(tmp_path):
    for name in ("cam", "cam-2", "cam-10", "camera", "cam-3"):
        (tmp_path / name).mkdir()
        (tmp_path / name / LAST).write_bytes(b"x")
    (tmp_path / "cam-11").mkdir()  # no checkpoint: not a run to resume
    assert newest_run(tmp_path, "cam") == tmp_path / "cam-10"
    with pytest.raises(FileNotFoundError, match="no run named 'other'"):
        newest_run(tmp_path, "other")


def test_resumed_config_is_the_runs_own_and_changes_are_refused(tmp_path):
    config, run = _run(tmp_path)
    assert resumed_config(run, None) == config
    moved = load_config(None, TINY + ["train.epochs=1", "train.warmup_epochs=0", "run.output_dir=elsewhere",
                                      "run.name=tiny"])
    assert resumed_config(run, moved).run.output_dir == str(tmp_path)  # where the run lives is not a change
    changed = load_config(None, TINY + ["train.epochs=5", "train.warmup_epochs=0", f"run.output_dir={tmp_path}",
                                        "run.name=tiny"])
    with pytest.raises(ConfigError, match=r"train.epochs: 1 -> 5.*--allow-config-change"):
        resumed_config(run, changed)
    assert resumed_config(run, changed, allow_change=True).train.epochs == 5


def test_resume_dir_alone_continues_with_the_runs_config(tmp_path, capsys):
    config, run = _run(tmp_path, extra=["train.epochs=2"])
    (run / "metrics.jsonl").write_text((run / "metrics.jsonl").read_text() + '{"epoch": 2, "trai')  # torn by a kill
    (run / engine.EVALUATION).unlink()  # killed after its last epoch, before its final evaluation: one to resume
    state = json.loads((run / "checkpoint_last.json").read_text())["state"]
    assert state["epoch"] == 1
    assert main(["train", "--resume-dir", str(run), "--no-progress"]) == 0
    assert f"resuming {run}: all 2 epochs trained; writing its final evaluation" in capsys.readouterr().out
    assert (run / engine.EVALUATION).is_file()
    assert [r["epoch"] for r in read_metrics(run / "metrics.jsonl", 10)] == [0, 1]
    # --resume finds the newest run of the name; a changed --set is refused before anything is written
    assert main(["train", "--resume", "--set", f"run.output_dir={tmp_path}", "--set", "run.name=tiny",
                 "--set", "train.epochs=3"]) == 2
    assert "train.epochs: 2 -> 3" in capsys.readouterr().err


def test_resuming_a_finished_run_says_so_and_changes_nothing(tmp_path, capsys):
    """It printed "resuming <run> from epoch 3/2", evaluated the run again and rewrote its evaluation."""
    _, run = _run(tmp_path, extra=["train.epochs=2"])
    capsys.readouterr()
    before = {path.name: path.read_bytes() for path in run.iterdir()}
    assert main(["train", "--resume-dir", str(run), "--no-progress"]) == 0
    assert capsys.readouterr().out.strip() == (f"{run}: already finished (2 of 2 epochs); nothing to resume "
                                               "(--extend N trains N more)")
    assert {path.name: path.read_bytes() for path in run.iterdir()} == before


def test_extend_trains_more_epochs_of_a_finished_run_and_keeps_the_old_config(tmp_path, capsys):
    config, run = _run(tmp_path, extra=["train.epochs=2", "train.warmup_epochs=1", "train.time_budget_minutes=60"])
    assert main(["train", "--resume-dir", str(run), "--extend", "1", "--no-progress"]) == 0
    assert f"resuming {run} from epoch 3/3" in capsys.readouterr().out
    assert [r["epoch"] for r in read_metrics(run / "metrics.jsonl", 10)] == [0, 1, 2]
    now = json.loads((run / "config.json").read_text())["train"]
    before = json.loads((run / "config.epoch2.json").read_text())["train"]
    assert (now["epochs"], now["warmup_epochs"], now["time_budget_minutes"]) == (3, 1, 0.0)
    assert (before["epochs"], before["time_budget_minutes"]) == (2, 60)
    assert json.loads((run / "checkpoint_last.json").read_text())["state"]["epoch"] == 2
    # a plain resume of the extended run changes nothing and keeps no copy
    assert main(["train", "--resume-dir", str(run), "--no-progress"]) == 0
    assert sorted(p.name for p in run.glob("config*.json")) == ["config.epoch2.json", "config.json"]
    assert main(["train", "--extend", "2", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "give --resume or --resume-dir" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(SystemExit) as exited:  # the parser refuses a count below 1
        main(["train", "--resume-dir", str(run), "--extend", "0", "--no-progress"])
    assert exited.value.code == 2 and "argument --extend: must be >= 1, got 0" in capsys.readouterr().err


def test_metrics_up_to_an_epoch_or_all_and_a_torn_last_line_dropped(tmp_path):
    path = tmp_path / "metrics.jsonl"
    path.write_text('{"epoch": 0}\n{"epoch": 1}\n\n{"epoch": 2}\n{"epo')
    assert [r["epoch"] for r in read_metrics(path, 1)] == [0, 1]
    assert [r["epoch"] for r in read_metrics(path)] == [0, 1, 2]
    assert read_metrics(tmp_path / "none.jsonl") == []


def test_torn_metrics_line_in_the_middle_is_an_error(tmp_path):
    path = tmp_path / "metrics.jsonl"
    path.write_text('{"epoch": 0}\n{"epo\n{"epoch": 1}\n')
    with pytest.raises(ValueError, match=r"metrics.jsonl:2: not a JSON record"):
        read_metrics(path, 5)


def test_run_lock_refuses_a_second_training_and_takes_over_a_stale_lock(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    with RunLock(tmp_path):
        with pytest.raises(FileExistsError, match="in use by process"):
            RunLock(tmp_path).acquire()
    assert not (tmp_path / "train.lock").exists()
    (tmp_path / "train.lock").write_text(dead.stdout.strip())  # left by a process that has exited (a pid alone)
    with RunLock(tmp_path):
        assert (tmp_path / "train.lock").read_text() == f"{os.getpid()} {socket.gethostname()}"


def test_run_lock_of_another_host_is_refused_naming_it_and_taken_over_by_a_slurm_task(tmp_path, monkeypatch):
    """A lock of another node (a run directory on a shared disk) holds a pid that means nothing here: checked
    against this machine's processes, a Slurm task requeued after its first was killed was refused whenever that pid
    happened to be in use here (or took over a live run's lock elsewhere). Now: refused naming the host, except by a
    Slurm task (its cell's task runs once: the lock is the killed one's); `holder` does not name a remote pid."""
    monkeypatch.delenv("SLURM_JOB_ID", raising=False)
    (tmp_path / "train.lock").write_text(f"{os.getpid()} another-node")  # a pid that is alive here
    assert RunLock(tmp_path).holder() is None
    with pytest.raises(FileExistsError, match=f"locked by process {os.getpid()} on another-node"):
        RunLock(tmp_path).acquire()
    monkeypatch.setenv("SLURM_JOB_ID", "7")
    with RunLock(tmp_path):
        assert (tmp_path / "train.lock").read_text() == f"{os.getpid()} {socket.gethostname()}"


def test_ctrl_c_prints_the_resume_command_and_releases_the_lock(tmp_path, monkeypatch, capsys):
    def interrupted_after_an_epoch(config, run_dir, *args, **kwargs):
        (run_dir / engine.LAST).write_bytes(b"")  # the first epoch's checkpoint
        raise KeyboardInterrupt

    monkeypatch.setattr(engine, "_train", interrupted_after_an_epoch)
    code = main(["train", "--set", f"run.output_dir={tmp_path}", "--set", "run.name=cut", "--no-progress"])
    assert code == 130
    assert f"continue with: warpsense train --resume-dir {tmp_path / 'cut'}" in capsys.readouterr().err
    assert not (tmp_path / "cut" / "train.lock").exists()


def test_ctrl_c_in_the_first_epoch_leaves_nothing_to_resume(tmp_path, monkeypatch, capsys):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(engine, "_train", interrupted)
    code = main(["train", "--set", f"run.output_dir={tmp_path / 'runs'}", "--set", "run.name=cut", "--no-progress"])
    assert code == 130
    error = capsys.readouterr().err
    assert "interrupted before the first epoch ended; nothing to resume" in error and "--resume-dir" not in error
    assert not (tmp_path / "runs").exists()  # the folders it made are gone


def test_runs_record_their_environment_and_files_get_the_default_mode(tmp_path):
    _, run = _run(tmp_path)
    environment = json.loads((run / "environment.json").read_text())
    assert environment["warpsense"] and environment["torch"] and environment["warp"]
    state = json.loads((run / "checkpoint_last.json").read_text())["state"]
    assert state["environment"] == environment
    umask = os.umask(0)
    os.umask(umask)
    for name in ("checkpoint_last.safetensors", "checkpoint_best.safetensors", "checkpoint_last.json"):
        assert (run / name).stat().st_mode & 0o777 == 0o666 & ~umask  # safetensors alone would write 0600


@pytest.mark.parametrize("command", [
    ["eval", "--checkpoint", "c.safetensors", "--json", "{missing}/m.json"],
    ["eval", "--checkpoint", "c.safetensors", "--json", "{folder}"],
    ["bench", "--quick", "--plot", "{missing}/p.png"],
    ["predict", "c.safetensors", "x.dng", "--out", "{missing}/p.png"],
    ["convert", "x.dng", "--out", "{file}"],
    ["train", "--set", "run.output_dir={file}"],
])
def test_output_paths_are_checked_before_any_work(tmp_path, capsys, command):
    """Issue 14 item 8: a folder where a file goes, a file where a folder goes, a missing folder: one line, exit 2,
    nothing written."""
    (tmp_path / "afile").write_text("x")
    names = {"missing": str(tmp_path / "no" / "such"), "folder": str(tmp_path), "file": str(tmp_path / "afile")}
    before = sorted(tmp_path.rglob("*"))
    assert main([part.format(**names) for part in command]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"warpsense {command[0]}: error:") and "\n" not in err
    assert sorted(tmp_path.rglob("*")) == before


def test_eval_latency_alone_reads_no_dataset_and_scores_nothing(tmp_path):
    from warpsense.commands.eval import run_eval

    _, run = _run(tmp_path)
    payload = run_eval(str(run / "checkpoint_last.safetensors"), "camvid", str(tmp_path / "no_dataset_here"), "val",
                       json_out=str(tmp_path / "latency.json"), latency=True, latency_size=(32, 48), device="cpu")
    assert "miou" not in payload
    assert {"sensor_plus_network_ms", "network_ms"} <= set(payload["latency"])
    assert payload["latency"]["sensor_plus_network_ms"] > 0 and payload["latency"]["camera_cached"] is True
    assert json.loads((tmp_path / "latency.json").read_text())["latency"] == payload["latency"]


def test_the_run_folder_names_its_files_as_they_are_on_disk(tmp_path):
    """RunDir is the one owner of a run folder's names; the module names callers wrote before it are the same."""
    from warpsense.train import inputs, run_dir

    run = RunDir(tmp_path / "run")
    assert {name: getattr(run, name).name for name in ("config", "metrics", "last", "best", "evaluation",
                                                        "environment", "inputs", "best_copy")} == {
        "config": "config.json", "metrics": "metrics.jsonl", "last": "checkpoint_last.safetensors",
        "best": "checkpoint_best.safetensors", "evaluation": "evaluation.json", "environment": "environment.json",
        "inputs": "inputs.json", "best_copy": "checkpoint_best.json"}
    assert run.earlier_config(3) == tmp_path / "run" / "config.epoch3.json"
    assert run.plot("curves") == tmp_path / "run" / "curves.png" and run.lock().path == tmp_path / "run" / "train.lock"
    assert (run_dir.LAST, run_dir.BEST, run_dir.METRICS, run_dir.LOCK, engine.EVALUATION, inputs.INPUTS) == (
        "checkpoint_last.safetensors", "checkpoint_best.safetensors", "metrics.jsonl", "train.lock",
        "evaluation.json", "inputs.json")
    assert os.fspath(run) == str(run) == str(tmp_path / "run")


def test_the_kept_best_score_comes_from_the_best_checkpoints_header(tmp_path):
    import torch

    from warpsense.system.checkpoint import save_checkpoint

    run = RunDir(tmp_path)
    assert run.kept_best() == -1.0 and run.checkpoint_state(run.last) is None  # none written yet
    save_checkpoint(run.best, torch.nn.Linear(1, 1), {}, {"epoch": 2, "best_miou": 0.375})
    assert run.kept_best() == 0.375 and run.checkpoint_state(run.best) == {"epoch": 2, "best_miou": 0.375}
    save_checkpoint(run.best, torch.nn.Linear(1, 1), {}, {"epoch": 2, "best_miou": float("nan")})
    assert run.kept_best() == -1.0  # not a score: the next best epoch writes it
    run.best.write_bytes(b"torn")
    assert run.kept_best() == -1.0 and run.checkpoint_state(run.best) is None
    assert run.holds_run() and not run.resumable() and not run.finished()


def test_a_changed_config_keeps_the_earlier_one_once(tmp_path):
    run = RunDir(tmp_path)
    first, second = load_config(None, TINY), load_config(None, [*TINY, "train.epochs=5"])
    run.write_config(first)
    run.write_config(first, continued_from=2)  # unchanged: nothing to keep
    assert not run.earlier_config(2).exists()
    run.write_config(second, continued_from=2)
    assert json.loads(run.earlier_config(2).read_text()) == json.loads(json.dumps(first.to_dict()))
    run.write_config(load_config(None, [*TINY, "train.epochs=6"]), continued_from=2)  # the first config stays kept
    assert json.loads(run.earlier_config(2).read_text()) == json.loads(json.dumps(first.to_dict()))
    assert run.saved_config().train.epochs == 6


def test_a_continuation_moves_the_earlier_ends_files_aside(tmp_path):
    run = RunDir(tmp_path)
    for name, text in (("evaluation.json", "{}"), ("curves.png", "a"), ("camera.epoch1.png", "b"),
                       ("config.json", "{}")):
        (tmp_path / name).write_text(text)
    run.supersede_final_files(4)
    assert sorted(path.name for path in tmp_path.iterdir()) == [
        "camera.epoch1.png", "config.json", "curves.epoch4.png", "evaluation.epoch4.json"]


def test_an_unfinished_run_leaves_nothing_but_a_best_checkpoint(tmp_path):
    created = tmp_path / "out"
    run = RunDir(created / "runs" / "a")
    run.path.mkdir(parents=True)
    run.write_metrics([{"epoch": 0}])
    run.remove_unfinished(created)
    assert not created.exists()
    run.path.mkdir(parents=True)
    run.best.write_bytes(b"")
    run.remove_unfinished(created)
    assert run.best.exists()  # that model is the user's
    run.best.unlink()
    run.remove_unfinished(None)  # made by someone else: kept
    assert run.path.is_dir()
