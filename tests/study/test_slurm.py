"""`warpsense study run --executor slurm` (submitit) and `warpsense study status`: the executor's options refused in one
line before anything is written or submitted, the status of each cell from the directory and the scheduler, and
(marked `slurm`) the smoke study through a real Slurm end to end: a task whose training process is killed mid-run,
another preempted (submitit checkpoints and requeues it), the study submitted again resumes the killed cell from its
checkpoint without retraining a finished one, and the report reads the directory.

The `slurm` tests need a Slurm controller that answers with a node taking jobs (`bash tools/slurm/local-cluster.sh
start` makes one on this machine, as root); they skip, with the reason, where there is none.
"""

import functools
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from tests.reliability.conftest import assert_clean_failure
from warpsense.cli import main
from warpsense.study import load_plan, slurm, slurm_status, work
from warpsense.study.study_dir import StudyDir, record_plan, run_dir

FAST = ["train.epochs=8", "data.scenes_train=16", "data.scenes_val=4", "train.eval_every=8"]
EPOCHS = 8
SETS = sum((["--set", text] for text in FAST), [])


@functools.lru_cache(maxsize=None)
def _slurm_missing() -> str | None:
    """Why no Slurm can take jobs here (None: one can); asked once (a controller that is down answers slowly)."""
    for command in ("sinfo", "sbatch", "squeue", "scancel", "srun"):
        if shutil.which(command) is None:
            return f"{command} not found (start a local Slurm: bash tools/slurm/local-cluster.sh start)"
    try:
        ping = subprocess.run(["scontrol", "ping"], capture_output=True, text=True, timeout=20)
        nodes = subprocess.run(["sinfo", "-h", "-N", "-o", "%T"], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as error:
        return f"the Slurm controller does not answer: {error}"
    if "is UP" not in ping.stdout:
        answer = (ping.stdout + ping.stderr).strip().splitlines()
        return f"the Slurm controller does not answer ({answer[0] if answer else f'exit status {ping.returncode}'})"
    if not any(state.startswith(("idle", "mixed", "allocated")) for state in nodes.stdout.split()):
        return f"no Slurm node takes jobs (sinfo: {nodes.stdout.strip() or nodes.stderr.strip()})"
    return None


@pytest.fixture
def cluster():
    reason = _slurm_missing()
    if reason:
        pytest.skip(f"no Slurm: {reason}")


# -- the executor's options, without Slurm --------------------------------------------------------------------------

BAD_OPTIONS = [
    (["--executor", "slurm", "--slurm-partition", "gpu queue"], ("--slurm-partition", "'gpu queue'", "partition name")),
    (["--executor", "slurm", "--slurm-partition", "a,,b"], ("--slurm-partition",)),
    (["--executor", "slurm", "--slurm-time", "0"], ("--slurm-time", "positive", "got 0")),
    (["--executor", "slurm", "--slurm-time", "-5"], ("--slurm-time", "got -5")),
    (["--executor", "slurm", "--gpus-per-cell", "-1"], ("--gpus-per-cell", ">= 0")),
    (["--executor", "slurm", "--array-parallelism", "0"], ("--array-parallelism", ">= 1")),
    (["--executor", "slurm", "--slurm-option", "=high"], ("--slurm-option", "'=high'", "KEY=VALUE")),
    (["--executor", "slurm", "--slurm-option", "qos="], ("--slurm-option", "'qos='")),
    (["--executor", "slurm", "--slurm-option", "array=0-3"], ("--slurm-option", "--array", "--array-parallelism")),
    (["--executor", "slurm", "--slurm-option", "time=10"], ("--slurm-option", "--slurm-time")),
    (["--executor", "slurm", "--plan-only"], ("--plan-only", "--executor slurm")),
    (["--slurm-partition", "gpu"], ("--slurm-partition", "--executor slurm")),
    (["--wait"], ("--wait", "--executor slurm")),
    (["--executor", "slurm", "--set", "train.nope=1"], ("train.nope",)),
]


@pytest.mark.parametrize("arguments, names", BAD_OPTIONS, ids=[f"bad{i}" for i in range(len(BAD_OPTIONS))])
def test_bad_executor_options_are_one_line_errors_before_anything_is_written(arguments, names, tmp_path, capsys,
                                                                             monkeypatch):
    real_run = subprocess.run

    def no_slurm(command, *args, **kwargs):  # nothing reaches Slurm
        assert Path(command[0]).name not in ("sbatch", "squeue", "srun", "scancel"), f"Slurm asked: {command}"
        return real_run(command, *args, **kwargs)

    monkeypatch.setattr(subprocess, "run", no_slurm)
    assert_clean_failure(capsys, ["study", "run", "smoke", "--out", str(tmp_path / "study"), *arguments], names,
                         watched=tmp_path)


def test_missing_slurm_commands_are_a_one_line_error_naming_the_executor(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))  # no sbatch, squeue or srun
    assert_clean_failure(capsys, ["study", "run", "smoke", "--out", str(tmp_path / "study"), "--executor", "slurm"],
                         ("--executor slurm", "sbatch, squeue, srun", "not found"), watched=tmp_path)


def test_slurm_options_map_onto_submitit_and_sbatch():
    options = slurm.slurm_options("slurm", "gpu,gpu-long", 90, 2, 4, ["qos=high", "--account=vision", "exclusive",
                                                                       "cpus_per_task=8"])
    assert options.extra == (("qos", "high"), ("account", "vision"), ("exclusive", True), ("cpus-per-task", "8"))
    assert slurm._sbatch_flags(options, 2, 6) == [
        "--array=0-5%4", "--time=90", "--partition=gpu,gpu-long", "--gpus-per-node=2", "--qos=high",
        "--account=vision", "--exclusive", "--cpus-per-task=8"]
    assert slurm.slurm_options("local") is None
    defaults = slurm.slurm_options("slurm")
    assert (defaults.time_minutes, defaults.array_parallelism, defaults.gpus_per_cell) == (60, 256, None)
    plan = load_plan("smoke")  # run.device = "cpu": no GPU asked for unless --gpus-per-cell says so
    assert slurm.default_gpus(plan, Path("out"), plan.cells()) == 0


def test_status_reads_the_directory_and_the_queue(tmp_path, monkeypatch, capsys):
    """Each cell: done (evaluated), running or pending as squeue lists its task, failed where its task is gone
    without an evaluation (the reason from its log), pending where never submitted (with its checkpoint)."""
    from warpsense.train.run_dir import LAST, METRICS

    plan = load_plan("smoke", FAST)
    out = tmp_path / "study"
    record_plan(plan, out)
    done, running, queued, failed, fresh, partial = plan.cells()
    for cell in (done, running, failed, partial):
        folder = run_dir(out, cell)
        folder.mkdir(parents=True)
        (folder / LAST).write_bytes(b"")
        (folder / METRICS).write_text(json.dumps({"epoch": 0}) + "\n" + json.dumps({"epoch": 1}) + "\n")
        (folder / "config.json").write_text(json.dumps({"train": {"epochs": EPOCHS}}))
    (run_dir(out, done) / "evaluation.json").write_text(json.dumps({"splits": {"val": {"miou": 0.25}}}))
    ids = {done.id: "7_0", running.id: "7_1", queued.id: "7_2", failed.id: "7_3"}
    (out / "slurm").mkdir()
    (out / StudyDir.JOBS).write_text(json.dumps({"submissions": [{"job_id": "7", "cells": ids}]}))
    log = out / "slurm" / "7_3" / "7_3_0_log.err"
    log.parent.mkdir()
    log.write_text("slurmstepd: error: *** STEP 7.0 ON vm CANCELLED AT 2026-01-01T00:00:00 ***\n")
    monkeypatch.setattr(slurm_status, "queue_states",
                        lambda: {"7_1": ("RUNNING", "None"), "7_2": ("PENDING", "Resources")})

    assert main(["study", "status", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"study smoke: 6 cells in {out} (Slurm job 7)"
    rows = {line.split()[0]: line.split(None, 2)[1:] for line in lines[1:7]}
    assert rows[done.id] == ["done", "val mIoU 0.2500"]
    assert rows[running.id] == ["running", f"job 7_1, epoch 2 of {EPOCHS}"]
    assert rows[queued.id] == ["pending", "job 7_2 pending (Resources)"]
    assert rows[failed.id][0] == "failed" and f"job 7_3 ended, stopped at epoch 2 of {EPOCHS}" in rows[failed.id][1]
    assert "CANCELLED" in rows[failed.id][1]
    assert rows[fresh.id] == ["pending", "not started"]
    assert rows[partial.id] == ["pending", f"stopped at epoch 2 of {EPOCHS}, resumes from its last checkpoint"]
    assert lines[7] == "6 cells: 1 done, 1 running, 3 pending, 1 failed"
    assert_clean_failure(capsys, ["study", "status", str(tmp_path / "nowhere")], ("no such study directory",))


def test_status_of_a_stopped_cell_names_the_epoch_it_resumes_after(tmp_path):
    """A cell stopped here, never submitted: with train.checkpoint_every > 1 (the camvid presets: 5) its resume point
    lies before the last epoch metrics.jsonl records, and before its first checkpoint there is none (the next run
    trains it from the start); the status said 'resumes there' at the last recorded epoch in both cases."""
    import torch
    from safetensors.torch import save_file

    from warpsense.system.checkpoint import METADATA_KEY
    from warpsense.train.run_dir import LAST, METRICS

    plan = load_plan("smoke", FAST)
    out = tmp_path / "study"
    record_plan(plan, out)
    behind, level, unsaved = plan.cells()[:3]
    for cell, saved_epoch in ((behind, 4), (level, 6), (unsaved, None)):
        folder = run_dir(out, cell)
        folder.mkdir(parents=True)
        (folder / METRICS).write_text("".join(json.dumps({"epoch": epoch}) + "\n" for epoch in range(7)))
        (folder / "config.json").write_text(json.dumps({"train": {"epochs": EPOCHS}}))
        if saved_epoch is not None:
            save_file({"model.w": torch.zeros(1)}, str(folder / LAST),
                      metadata={METADATA_KEY: json.dumps({"config": {}, "state": {"epoch": saved_epoch}})})
    detail = {cell: slurm_status.cell_status(out, cell, None, None) for cell in (behind, level, unsaved)}
    assert {status.state for status in detail.values()} == {"pending"}
    assert detail[behind].detail == f"stopped at epoch 7 of {EPOCHS}, resumes after epoch 5 (its last checkpoint)"
    assert detail[level].detail == f"stopped at epoch 7 of {EPOCHS}, resumes there"
    assert detail[unsaved].detail == (f"stopped at epoch 7 of {EPOCHS} before its first checkpoint, trains from the "
                                      "start")


def test_status_names_a_cell_whose_metrics_are_damaged_and_shows_the_others(tmp_path, capsys):
    """A damaged line inside one cell's metrics.jsonl (not its torn last line) failed the whole `study status`."""

    plan = load_plan("smoke", FAST)
    out = tmp_path / "study"
    record_plan(plan, out)
    damaged, other = plan.cells()[:2]
    for cell, text in ((damaged, '{"epoch": 0}\nnot json\n{"epoch": 2}\n'), (other, '{"epoch": 0}\n')):
        run_dir(out, cell).mkdir(parents=True)
        (run_dir(out, cell) / "metrics.jsonl").write_text(text)
    assert main(["study", "status", str(out)]) == 0
    printed = capsys.readouterr().out
    metrics = run_dir(out, damaged) / "metrics.jsonl"
    assert f"stopped at epoch ? ({metrics}:2: not a JSON record)" in printed
    assert "stopped at epoch 1 of " in printed  # the other cell's own line


def test_a_local_run_refuses_cells_that_slurm_tasks_hold(tmp_path, monkeypatch, capsys):
    """`study run` without --executor slurm on a study whose cells are queued or running on Slurm trained them here
    too, into the same run directories (the run lock sees processes of this machine only); it is refused in one line
    naming the cells and their tasks, before anything is written. A task that has ended holds nothing."""

    plan = load_plan("smoke", FAST)
    out = tmp_path / "study"
    record_plan(plan, out)
    cells = plan.cells()
    (out / "slurm").mkdir()
    (out / StudyDir.JOBS).write_text(json.dumps({"submissions": [{"job_id": "7", "cells": {
        cells[0].id: "7_0", cells[1].id: "7_1", cells[2].id: "7_2"}}]}))
    monkeypatch.setattr(slurm_status, "queue_states",
                        lambda: {"7_0": ("RUNNING", "None"), "7_1": ("PENDING", "Priority")})
    run = ["study", "run", "smoke", "--out", str(out), "--gpus", "none", *SETS]
    assert_clean_failure(capsys, run, (f"{cells[0].id} (job 7_0)", f"{cells[1].id} (job 7_1)", "queued or running"),
                         watched=tmp_path)
    assert cells[2].id not in capsys.readouterr().err
    assert_clean_failure(capsys, [*run, "--cell", cells[1].id], (f"{cells[1].id} (job 7_1)",), watched=tmp_path)
    monkeypatch.setattr(slurm_status, "queue_states", lambda: None)  # no squeue here: said, and not refused
    slurm_status.check_not_queued(out, cells)
    assert "squeue does not answer" in capsys.readouterr().err


def test_submitting_refuses_cells_a_local_run_trains_now(tmp_path, monkeypatch, capsys):
    """--executor slurm submitted a cell that a local `study run` of this machine was training (its run lock held by
    a live process): the task, on another node, would have taken the run directory over. Refused in one line naming
    the cell and the process; nothing submitted or written."""

    plan = load_plan("smoke", FAST)
    out = tmp_path / "study"
    record_plan(plan, out)
    busy = plan.cells()[1]
    run_dir(out, busy).mkdir(parents=True)
    (run_dir(out, busy) / "train.lock").write_text(str(os.getpid()))  # a live process holds it
    monkeypatch.setattr(slurm, "require_slurm", lambda: None)
    monkeypatch.setattr(slurm, "check_submission", lambda *args: pytest.fail("asked Slurm"))
    monkeypatch.setattr(slurm, "submit", lambda *args: pytest.fail("submitted"))
    assert_clean_failure(capsys, ["study", "run", "smoke", "--out", str(out), "--executor", "slurm", *SETS],
                         (f"{busy.id} (process {os.getpid()})", "training on this machine", "nothing submitted"),
                         watched=tmp_path)
    # a cell submitted before, whose task is gone: its lock is the killed task's (a pid of another node), not a local
    # run's, and the cell is submitted again
    (out / StudyDir.JOBS).parent.mkdir()
    (out / StudyDir.JOBS).write_text(json.dumps({"submissions": [{"job_id": "7", "cells": {busy.id: "7_1"}}]}))
    monkeypatch.setattr(slurm_status, "queue_states", lambda: {})
    monkeypatch.setattr(slurm, "check_submission", lambda *args: None)
    submitted = []
    monkeypatch.setattr(slurm, "submit", lambda plan, out, cells, options, gpus: submitted.extend(cells) or "8")
    assert main(["study", "run", "smoke", "--out", str(out), "--executor", "slurm", *SETS]) == 0
    assert busy in submitted


def test_the_job_array_holds_the_longest_cells_first(tmp_path, monkeypatch, capsys):
    """Slurm starts an array's tasks by index: the cells go in longest first (`warpsense.study.work.cell_work`), ties
    in plan order, so that with fewer nodes than cells the short ones fill the end (as the local pool hands them
    out)."""

    frames = {"rggb": 1, "rccb": 3, "learned": 2}
    monkeypatch.setattr(work, "cell_work", lambda plan, cells: {cell: frames[cell.camera] for cell in cells})
    monkeypatch.setattr(slurm, "require_slurm", lambda: None)
    monkeypatch.setattr(slurm, "check_submission", lambda *args: None)
    submitted = []
    monkeypatch.setattr(slurm, "submit", lambda plan, out, cells, options, gpus: submitted.extend(cells) or "7")
    assert main(["study", "run", "smoke", "--out", str(tmp_path / "study"), "--executor", "slurm", *SETS]) == 0
    assert [cell.id for cell in submitted] == ["rccb/night/0", "rccb/night/1", "learned/night/0", "learned/night/1",
                                               "rggb/night/0", "rggb/night/1"]


# -- a real Slurm -----------------------------------------------------------------------------------------------------


@pytest.mark.slurm
@pytest.mark.parametrize("arguments, names", [
    (["--slurm-partition", "no_such_partition"], ("--slurm-partition no_such_partition", "invalid partition")),
    (["--slurm-option", "no-such-option=1"], ("--slurm-option no-such-option", "sbatch does not know")),
    (["--gpus-per-cell", "64"], ("--gpus-per-cell 64",)),
], ids=["partition", "option", "gpus"])
def test_options_slurm_refuses_are_one_line_errors_with_nothing_submitted(arguments, names, cluster, tmp_path,
                                                                          capsys):
    before = slurm_status.queue_states()
    assert_clean_failure(capsys, ["study", "run", "smoke", "--out", str(tmp_path / "study"), "--executor", "slurm",
                                  *arguments], names, watched=tmp_path)
    assert slurm_status.queue_states() == before


def _wait_for(condition, what: str, timeout: float = 60.0):
    deadline = time.time() + timeout
    while not condition():
        if time.time() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def _processes(metrics: Path) -> int:
    """How many processes trained a run (each one's first record holds setup_s)."""
    return sum("setup_s" in json.loads(line) for line in metrics.read_text().splitlines() if line.strip())


@pytest.mark.slurm
def test_smoke_study_on_slurm_killed_and_preempted_tasks_resume(cluster, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(slurm, "POLL_SECONDS", 0.5)
    out = tmp_path / "study"
    plan = load_plan("smoke", FAST)
    cells = plan.cells()
    preempted, killed = cells[0], cells[1]  # the array's first two tasks
    run = ["study", "run", "smoke", "--out", str(out), "--executor", "slurm", *SETS]

    assert main(run) == 0  # returns once submitted
    printed = capsys.readouterr().out
    assert "study: submitted 6 cell(s) (0 resuming from a checkpoint) as Slurm job" in printed
    first = slurm_status.latest_jobs(out)
    assert list(first) == [cell.id for cell in cells]

    def checkpointed(cell):
        return (out / "runs" / cell.run_name / "checkpoint_last.safetensors").is_file()

    def kill(cell):
        # the task's training process (its step 0) killed mid-run, as the kernel's OOM killer would: the task ends,
        # failed. Sent to the process itself: a `scancel --signal KILL` of the step made slurmstepd drain the one
        # node ("Kill task failed") once when the process took longer than UnkillableStepTimeout to go
        os.kill(int((out / "runs" / cell.run_name / "train.lock").read_text().split()[0]), signal.SIGKILL)

    def preempt(cell):
        # preemption, or a time limit near: Slurm signals the task (USR2, as submitit's sbatch --signal asks), and
        # submitit checkpoints it and requeues it. The signal goes straight to the training process (its run
        # directory's lock holds its pid): `scancel --signal USR2` retries while submitit requeues the task, and
        # signals the requeued task again.
        os.kill(int((out / "runs" / cell.run_name / "train.lock").read_text().split()[0]), signal.SIGUSR2)

    actions = {killed: kill, preempted: preempt}  # each as soon as its cell's first epoch is written
    deadline = time.time() + 60
    while actions:
        assert time.time() < deadline, f"no checkpoint of {[cell.id for cell in actions]} in 60 s"
        for cell in [cell for cell in actions if checkpointed(cell)]:
            actions.pop(cell)(cell)
        time.sleep(0.05)
    _wait_for(lambda: first[killed.id] not in (slurm_status.queue_states() or {first[killed.id]: 0}),
              "the killed task to end", timeout=180.0)
    for cell in (killed, preempted):
        assert not (out / "runs" / cell.run_name / "evaluation.json").exists(), f"{cell.id} finished first"

    assert main(["study", "status", str(out)]) == 0
    status = {line.split()[0]: line for line in capsys.readouterr().out.splitlines() if line.startswith("  ")}
    assert " failed " in status[killed.id] and f"job {first[killed.id]} ended, stopped at epoch" in status[
        killed.id]

    assert main(run + ["--wait"]) == 0  # the killed cell again; the others followed where they run
    printed = capsys.readouterr()
    assert "study: submitted 1 cell(s) (1 resuming from a checkpoint)" in printed.out
    assert "not submitted again" in printed.out and "study finished; report:" in printed.out
    submissions = slurm_status.read_jobs(out)
    assert len(submissions) == 2 and list(submissions[1]["cells"]) == [killed.id]
    for cell in cells:
        assert f"{cell.id}: done after" in printed.out or f"{cell.id}: finished earlier" in printed.out
        metrics = out / "runs" / cell.run_name / "metrics.jsonl"
        epochs = [json.loads(line)["epoch"] for line in metrics.read_text().splitlines()]
        assert epochs == list(range(EPOCHS)), (cell.id, epochs)  # each epoch once: resumed, not redone
        assert _processes(metrics) == (2 if cell in (preempted, killed) else 1), cell.id  # the rest trained once
    restarted = (out / "slurm" / first[preempted.id]).glob("*_log.out")
    assert "(restart 1)" in "".join(path.read_text() for path in restarted)  # the same task, requeued

    assert main(["study", "status", str(out)]) == 0
    assert "6 cells: 6 done, 0 running, 0 pending, 0 failed" in capsys.readouterr().out
    assert main(["study", "report", str(out), "--resamples", "50"]) == 0
    assert " evaluated, 0 missing;" in capsys.readouterr().out
