"""The state of every cell of a study directory (`warpsense study status`) and the Slurm tasks that hold them.

The ids of a study's submitted tasks are kept in its directory (`StudyDir.JOBS`); a cell is done (evaluated),
running or pending (queued or not submitted) as squeue says, or failed (its last task ended without finishing it, or
a local run recorded its failure). squeue rather than submitit's sacct watcher: sacct needs Slurm's accounting
database, which many small clusters (and tools/slurm/local-cluster.sh's) do without.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from warpsense.study.plan import Cell, Plan, PlanError
from warpsense.study.study_dir import StudyDir, read_record
from warpsense.study.training import score_line

ACTIVE = ("PENDING", "CONFIGURING", "RUNNING", "COMPLETING", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED", "RESIZING",
          "SUSPENDED", "STOPPED", "SIGNALING", "STAGE_OUT", "RESV_DEL_HOLD")
"""squeue states of a task that still holds its cell (queued, running or being requeued)."""


def read_jobs(out: Path) -> list[dict]:
    """The study directory's Slurm submissions, oldest first (`StudyDir.read_jobs`)."""
    return StudyDir(out).read_jobs()


def latest_jobs(out: Path) -> dict[str, str]:
    """Each submitted cell's latest task id ("<array job>_<index>", or a job id)."""
    jobs: dict[str, str] = {}
    for submission in read_jobs(out):
        jobs.update(submission["cells"])
    return jobs


def queue_states() -> dict[str, tuple[str, str]] | None:
    """This user's Slurm tasks as squeue lists them (arrays one line per task): id to (state, reason); None where
    squeue cannot be run or the controller does not answer."""
    try:
        result = subprocess.run(["squeue", "--me", "--noheader", "--array", "--format=%i|%T|%r"], capture_output=True,
                                text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if result.returncode != 0:
        return None
    states = {}
    for line in result.stdout.splitlines():
        parts = line.strip().split("|")
        if len(parts) == 3:
            states[parts[0]] = (parts[1], parts[2])
    return states


def queued_cells(out: Path, cells: list[Cell]) -> dict[Cell, str] | None:
    """The cells of ``cells`` whose latest Slurm task (`latest_jobs`) squeue lists as queued or running (`ACTIVE`),
    with that task's id: cells no other run may train now. Empty where none was submitted; None where some were
    and squeue does not answer."""
    jobs = latest_jobs(out)
    if not any(cell.id in jobs for cell in cells):
        return {}
    queue = queue_states()
    if queue is None:
        return None
    return {cell: jobs[cell.id] for cell in cells if cell.id in jobs and jobs[cell.id] in queue
            and queue[jobs[cell.id]][0] in ACTIVE}


def check_not_queued(out: Path, cells: list[Cell]) -> None:
    """Refuse to train here (the local executor) cells that Slurm tasks of this study hold, queued or running: the
    two would write one run directory, and the run lock cannot see a process on another node. One-line PlanError
    naming them and their tasks; where squeue does not answer, a warning and no refusal (a copy of the study on a
    machine without Slurm)."""
    queued = queued_cells(out, cells)
    if queued is None:
        print(f"study: warning: squeue does not answer; {StudyDir(out).jobs} lists Slurm tasks, which may still "
              "train some of these cells", file=sys.stderr, flush=True)
    elif queued:
        held = ", ".join(f"{cell.id} (job {job})" for cell, job in queued.items())
        raise PlanError(f"{out}: {len(queued)} cell(s) are queued or running on Slurm: {held}; not trained here as "
                        f"well: follow them with `warpsense study status {out}`, or cancel them (scancel) first")


def _epochs(out: Path, cell: Cell) -> str:
    """"epoch k of n": the epochs the cell's run has finished, of its config's; "" before its first epoch."""
    run = StudyDir(out).run(cell)
    try:
        records = run.read_metrics()
    except ValueError as error:  # a damaged line in one cell's record: that cell's status says so, not every cell's
        return f"epoch ? ({error})"
    if not records:
        return ""
    epoch = records[-1].get("epoch")
    if isinstance(epoch, bool) or not isinstance(epoch, int):  # the cell's status names the damage, not every cell's
        return f"epoch ? ({run.metrics}: last record: epoch: expected an integer, got {epoch!r})"
    try:
        total = read_record(run.config, dict)["train"]["epochs"]
    except PlanError as error:  # one cell's damaged config: its status says so, as for its metrics above
        total = f"? ({error})"
    except (KeyError, TypeError):
        total = f"? ({run.config}: train.epochs: missing)"
    return f"epoch {epoch + 1} of {total}"


def _submitit_job(out: Path, job_id: str):
    import submitit

    return submitit.SlurmJob(folder=StudyDir(out).submitit, job_id=job_id)


def failure(out: Path, job_id: str) -> str:
    """Why a cell's task ended without finishing the cell: the exception it raised (submitit's result), or the last
    line of its log (Slurm's "CANCELLED ... DUE TO TIME LIMIT", a crash)."""
    from submitit.core.utils import pickle_load

    job = _submitit_job(out, job_id)
    with contextlib.suppress(Exception):
        outcome, trace = pickle_load(job.paths.result_pickle)
        if outcome == "error":
            lines = [line for line in str(trace).strip().splitlines() if line.strip()]
            return lines[-1].strip() if lines else "the task raised an error"
    for log in (job.paths.stderr, job.paths.stdout):
        with contextlib.suppress(OSError):
            lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()]
            if lines:
                return lines[-1]
    return "the task ended without finishing the cell (no log)"


@dataclass(frozen=True)
class CellStatus:
    """A cell's state in a study directory: "done", "running", "pending" or "failed", and a few words on it."""

    cell: Cell
    state: str
    detail: str


def cell_status(out: Path, cell: Cell, job_id: str | None, queue: dict[str, tuple[str, str]] | None) -> CellStatus:
    """One cell's `CellStatus`.

    Args:
        out: the study directory.
        cell: the cell.
        job_id: its latest Slurm task (`latest_jobs`); None if it was never submitted.
        queue: squeue's states (`queue_states`); None where the scheduler does not answer.

    Returns:
        "done" where its evaluation is written; "running" or "pending" while squeue lists its task so (or, never
        submitted, while a process of this machine holds its run directory); "failed" where its task is gone
        without finishing it, or a local run recorded its failure (`StudyDir.record_failure`); else "pending" (not
        started; stopped, which the next run resumes from its last checkpoint, or trains from the start where it
        stopped before its first; or the scheduler does not answer).
    """
    study = StudyDir(out)
    state = study.cell_state(cell)
    progress = _epochs(out, cell)
    if state == "done":
        try:
            return CellStatus(cell, "done", score_line(study.read_evaluation(cell)))
        except (OSError, ValueError, KeyError):
            return CellStatus(cell, "done", "evaluated")
    if job_id is not None and queue is not None and job_id in queue and queue[job_id][0] in ACTIVE:
        slurm_state, reason = queue[job_id]
        if slurm_state in ("RUNNING", "COMPLETING"):
            return CellStatus(cell, "running", f"job {job_id}" + (f", {progress}" if progress else ""))
        why = f" ({reason})" if reason and reason != "None" else ""
        return CellStatus(cell, "pending", f"job {job_id} {slurm_state.lower()}{why}"
                          + (f", {progress}" if progress else ""))
    if job_id is not None and queue is not None:
        where = f"stopped at {progress}" if progress else "no epoch finished"
        return CellStatus(cell, "failed", f"job {job_id} ended, {where}: {failure(out, job_id)}")
    if job_id is not None:
        return CellStatus(cell, "pending", f"submitted as job {job_id} (the scheduler does not answer)")
    pid = study.run(cell).lock().holder()  # never submitted: perhaps training here (the local executor)
    if pid is not None:
        return CellStatus(cell, "running", f"process {pid} on this machine" + (f", {progress}" if progress else ""))
    # never submitted and no process here holds it: not started, or stopped (a local run interrupted or failed), which
    # the next `study run` resumes from its last checkpoint: with train.checkpoint_every > 1 (the camvid presets: 5)
    # that can lie epochs before the last one metrics.jsonl records, and before the first there is none
    detail = _stopped(out, cell, state, progress)
    reason = study.recorded_failure(cell)  # a local run's failure (Slurm's are its tasks' states, above)
    return CellStatus(cell, "pending", detail) if reason is None else CellStatus(cell, "failed", f"{reason}; {detail}")


def _stopped(out: Path, cell: Cell, state: str, progress: str) -> str:
    """Where a cell that runs nowhere stands: not started, or stopped at an epoch and what the next run resumes."""
    if not progress:
        return "not started"
    if state != "partial":
        return f"stopped at {progress} before its first checkpoint, trains from the start"
    saved = _checkpoint_epochs(out, cell)
    if saved is None:
        return f"stopped at {progress}, resumes from its last checkpoint"
    if progress.startswith(f"epoch {saved} of "):
        return f"stopped at {progress}, resumes there"
    return f"stopped at {progress}, resumes after epoch {saved} (its last checkpoint)"


def _checkpoint_epochs(out: Path, cell: Cell) -> int | None:
    """The epochs the cell's last checkpoint (its resume point) holds, from its header (`RunDir.checkpoint_state`:
    no tensor is read); None where that cannot be read (the caller says "its last checkpoint")."""
    run = StudyDir(out).run(cell)
    epoch = (run.checkpoint_state(run.last) or {}).get("epoch")
    return epoch + 1 if isinstance(epoch, int) and not isinstance(epoch, bool) else None


def study_status(out: Path, plan: Plan, cells: list[Cell] | None = None) -> tuple[list[CellStatus], bool]:
    """Every cell's `CellStatus`, and whether the scheduler answered (True also where nothing was submitted)."""
    jobs = latest_jobs(out)
    queue = queue_states() if jobs else {}
    return [cell_status(out, cell, jobs.get(cell.id), queue) for cell in cells or plan.cells()], queue is not None


def print_status(study_dir: str | Path) -> int:
    """`warpsense study status DIR`: one line per cell (pending, running, done or failed, from the directory and the
    scheduler) and the counts."""
    from warpsense.study.adaptive import expected_cells

    out = Path(study_dir)
    record = StudyDir(out).read_plan()
    plan = Plan.from_dict(record)
    # study.sequential and [[search]]: the cells needed so far (a search's designs among them), not every seed
    statuses, answered = study_status(out, plan, expected_cells(out, record))
    submissions = read_jobs(out)
    jobs = f" (Slurm job{'s' if len(submissions) > 1 else ''} {', '.join(s['job_id'] for s in submissions)})" \
        if submissions else ""
    print(f"study {plan.name}: {len(statuses)} cells in {out}{jobs}")
    if not answered:
        print("study: squeue does not answer: the states of submitted cells are from the directory alone")
    width = max(len(status.cell.id) for status in statuses)
    for status in statuses:
        print(f"  {status.cell.id:<{width}}  {status.state:<7}  {status.detail}")
    counts = {state: sum(s.state == state for s in statuses) for state in ("done", "running", "pending", "failed")}
    print(f"{len(statuses)} cells: " + ", ".join(f"{count} {state}" for state, count in counts.items()))
    if counts["failed"]:
        print("failed cells resume from their last checkpoint when the study is run again")
    if counts["done"] == len(statuses):
        print(f"report: warpsense study report {out}")
    return 0
