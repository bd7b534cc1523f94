"""Running a study's cells on a Slurm cluster through submitit: the executor's options, the job array, and following
its tasks (the state of every cell of a study directory: `warpsense.study.slurm_status`).

`warpsense study run PLAN --out DIR --executor slurm` submits the cells that are neither finished nor queued as one
job array (`submitit.SlurmExecutor.map_array`), one cell per task, each task given its `Cell`; each task trains its
cell in the ordinary run directory in DIR (`warpsense.study.training.train_cell`), so that the report reads the same
directory whichever executor ran it. DIR must be on a file system the cluster's nodes share.

Resuming is the run directory's: a finished cell (its evaluation written) is never submitted again, and a cell whose
task was cancelled, killed, timed out or failed resumes from its last checkpoint when the study is submitted again.
A task that Slurm preempts, or whose time limit nears (Slurm's signal, ``--signal USR2@90`` as submitit asks it), is
checkpointed and requeued by submitit (`CellTask` is a `submitit.helpers.Checkpointable`: its checkpoint is the run
directory's last epoch, the call is the same) and resumes in the same array task.

The ids of the submitted tasks are kept in the study directory (`StudyDir.JOBS`); `warpsense study status DIR`
reads them with the directory (`warpsense.study.slurm_status`).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

# the names imported "as" themselves are what `warpsense study run | status` (warpsense.study.launch) import from
# here; they are slurm_status's
from warpsense.study import slurm_status, training, work
from warpsense.study.plan import Cell, Plan
from warpsense.study.reuse import finished_runs, reuse_cells
from warpsense.study.slurm_status import cell_status, latest_jobs, queued_cells
from warpsense.study.slurm_status import check_not_queued as check_not_queued
from warpsense.study.slurm_status import print_status as print_status
from warpsense.study.study_dir import StudyDir

try:
    from submitit.helpers import Checkpointable
except ImportError:  # without submitit the local executor and `study status` work; `require_slurm` says what to install
    Checkpointable = object

EXECUTORS = ("local", "slurm")

POLL_SECONDS = 10.0
"""How often `--wait` asks squeue."""

DEFAULT_TIME_MINUTES = 60
DEFAULT_ARRAY_PARALLELISM = 256  # submitit's

PARTITION_NAME = re.compile(r"^[A-Za-z0-9_.-]+(,[A-Za-z0-9_.-]+)*$")
SBATCH_KEY = re.compile(r"^[A-Za-z][A-Za-z0-9_-]*$")
MANAGED = {"array": "--array-parallelism", "partition": "--slurm-partition", "time": "--slurm-time",
           "gpus-per-node": "--gpus-per-cell", "output": None, "error": None, "open-mode": None, "signal": None,
           "wrap": None, "test-only": None}
"""sbatch options the executor sets itself (and the option of this command that sets each, where there is one)."""

@dataclass(frozen=True)
class SlurmOptions:
    """The Slurm executor's options, checked (`slurm_options`).

    Attributes:
        partition: sbatch --partition (None: the cluster's default partition).
        time_minutes: each task's time limit (sbatch --time); a cell that needs longer is checkpointed and requeued
            by submitit (up to 3 times).
        gpus_per_cell: sbatch --gpus-per-node of each task (None: 0 where every cell's config runs on the CPU,
            else 1).
        array_parallelism: tasks of the array running at once (sbatch --array=...%N).
        extra: further sbatch options, name (without dashes) to value (True: a flag without value).
        wait: follow the tasks until every cell has finished or failed.
    """

    partition: str | None = None
    time_minutes: int = DEFAULT_TIME_MINUTES
    gpus_per_cell: int | None = None
    array_parallelism: int = DEFAULT_ARRAY_PARALLELISM
    extra: tuple[tuple[str, str | bool], ...] = ()
    wait: bool = False


def sbatch_option(text: str) -> tuple[str, str | bool]:
    """One ``--slurm-option`` (``KEY=VALUE``, or ``KEY`` for a flag such as ``exclusive``) as (key, value)."""
    key, sep, value = text.partition("=")
    key = key.strip().lstrip("-").replace("_", "-")
    if not SBATCH_KEY.match(key) or (sep and not value.strip()):
        raise ValueError(f"--slurm-option {text!r}: expected KEY=VALUE, an sbatch option without its dashes (e.g. "
                         "qos=high, cpus-per-task=8), or KEY alone for a flag (e.g. exclusive)")
    if key in MANAGED:
        instead = f"; use {MANAGED[key]}" if MANAGED[key] else ""
        raise ValueError(f"--slurm-option {text!r}: --{key} is set by the executor{instead}")
    return key, value.strip() if sep else True


def slurm_options(executor: str, partition: str | None = None, time_minutes: int | None = None,
                  gpus_per_cell: int | None = None, array_parallelism: int | None = None,
                  extra: list[str] | tuple[str, ...] = (), wait: bool = False) -> SlurmOptions | None:
    """Check the executor options of `warpsense study run` without asking Slurm.

    Args:
        executor: "local" or "slurm" (`EXECUTORS`).
        partition, time_minutes, gpus_per_cell, array_parallelism: ``--slurm-partition``, ``--slurm-time``,
            ``--gpus-per-cell`` and ``--array-parallelism``; None where not given.
        extra: the ``--slurm-option`` texts (`sbatch_option`).
        wait: ``--wait``.

    Returns:
        The Slurm executor's `SlurmOptions`, or None for the local executor (which takes none of them).

    Raises:
        ValueError: a one-line message naming the option.
    """
    if executor not in EXECUTORS:
        raise ValueError(f"--executor must be one of {', '.join(EXECUTORS)}, got {executor!r}")
    given = {"--slurm-partition": partition, "--slurm-time": time_minutes, "--gpus-per-cell": gpus_per_cell,
             "--array-parallelism": array_parallelism, "--slurm-option": list(extra) or None, "--wait": wait or None}
    if executor == "local":
        for option, value in given.items():
            if value is not None:
                raise ValueError(f"{option} is an option of --executor slurm (the local executor runs the cells here "
                                 "and waits for them)")
        return None
    if partition is not None and not PARTITION_NAME.match(partition):
        raise ValueError(f"--slurm-partition {partition!r}: not a partition name (letters, digits, '_', '-' and '.'; "
                         "several separated by commas)")
    if time_minutes is not None and time_minutes < 1:
        raise ValueError(f"--slurm-time must be a positive number of minutes, got {time_minutes}")
    if gpus_per_cell is not None and gpus_per_cell < 0:
        raise ValueError(f"--gpus-per-cell must be >= 0, got {gpus_per_cell}")
    if array_parallelism is not None and array_parallelism < 1:
        raise ValueError(f"--array-parallelism must be >= 1, got {array_parallelism}")
    options = dict(sbatch_option(text) for text in extra)
    return SlurmOptions(partition, DEFAULT_TIME_MINUTES if time_minutes is None else time_minutes, gpus_per_cell,
                        DEFAULT_ARRAY_PARALLELISM if array_parallelism is None else array_parallelism,
                        tuple(options.items()), wait)


def require_slurm() -> None:
    """Refuse the Slurm executor where submitit or Slurm's commands are missing (one-line ValueError)."""
    if Checkpointable is object:
        raise ValueError("--executor slurm needs the submitit package: pip install 'warpsense[slurm]'")
    missing = [command for command in ("sbatch", "squeue", "srun") if shutil.which(command) is None]
    if missing:
        raise ValueError(f"--executor slurm: Slurm's {', '.join(missing)} not found on PATH (submit from a machine "
                         "of the cluster, or start one: bash tools/slurm/local-cluster.sh start)")


def _sbatch_flags(options: SlurmOptions, gpus: int, count: int) -> list[str]:
    """The sbatch options of a job array of ``count`` cells (what `submit` asks submitit for)."""
    flags = [f"--array=0-{count - 1}%{min(count, options.array_parallelism)}", f"--time={options.time_minutes}"]
    if options.partition:
        flags.append(f"--partition={options.partition}")
    if gpus:
        flags.append(f"--gpus-per-node={gpus}")
    return flags + [f"--{key}" if value is True else f"--{key}={value}" for key, value in options.extra]


def _described(options: SlurmOptions, gpus: int) -> str:
    words = [f"--slurm-partition {options.partition}" if options.partition else "the default partition",
             f"--slurm-time {options.time_minutes}", f"--gpus-per-cell {gpus}"]
    return ", ".join(words + [f"--slurm-option {key}" + ("" if value is True else f"={value}")
                              for key, value in options.extra])


def check_submission(options: SlurmOptions, gpus: int, count: int) -> None:
    """Ask Slurm whether it would take the job array (``sbatch --test-only``: nothing is submitted); a refusal is a
    one-line ValueError naming the option it concerns."""
    command = ["sbatch", "--test-only", *_sbatch_flags(options, gpus, count), "--output=/dev/null", "--wrap=true"]
    try:
        result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        raise ValueError("--executor slurm: the Slurm controller did not answer sbatch --test-only in 120 s") from None
    if result.returncode == 0:
        return
    lines = [line.strip() for line in (result.stderr + result.stdout).splitlines() if line.strip()]
    message = next((line for line in lines if "error" in line.lower() or "unrecognized" in line.lower()),
                   lines[0] if lines else f"exit status {result.returncode}")
    message = message.removeprefix("sbatch: error: ").removeprefix("Batch job submission failed: ")
    lowered = message.lower()
    unknown = re.search(r"unrecognized option '--([^'=]+)", message)
    if unknown:
        raise ValueError(f"--slurm-option {unknown.group(1)}: sbatch does not know this option ({message})")
    if "unable to contact" in lowered or "connection refused" in lowered or "connect failure" in lowered:
        raise ValueError(f"--executor slurm: the Slurm controller does not answer ({message})")
    if "partition" in lowered:
        raise ValueError(f"--slurm-partition {options.partition or '(default)'}: Slurm refused it ({message})")
    if "time limit" in lowered:
        raise ValueError(f"--slurm-time {options.time_minutes}: Slurm refused it ({message})")
    if gpus and ("gres" in lowered or "gpu" in lowered or "node configuration" in lowered):
        raise ValueError(f"--gpus-per-cell {gpus}: Slurm refused it ({message})")
    raise ValueError(f"--executor slurm: Slurm refused the job array ({_described(options, gpus)}): {message}")


class CellTask(Checkpointable):
    """One array task: trains (or resumes) one cell and returns its evaluation record.

    It holds the plan's file, the command line's overrides and the study directory, and reloads the plan in the
    task. As a `submitit.helpers.Checkpointable`, a task Slurm preempts or whose time runs out is requeued with the
    same call, which resumes the cell from the last checkpoint its run directory holds.
    """

    def __init__(self, plan_source: str, overrides: tuple[str, ...], out: str):
        self.plan_source, self.overrides, self.out = plan_source, tuple(overrides), out

    def __call__(self, cell: Cell | str) -> dict:
        """Train ``cell`` (a `Cell` of the plan, as submitted; a cell id from a submission of an earlier version)."""
        import torch

        from warpsense.study.plan import PlanError, load_plan

        cpus = os.environ.get("SLURM_CPUS_PER_TASK") or os.environ.get("SLURM_CPUS_ON_NODE")
        if cpus and cpus.isdigit() and "OMP_NUM_THREADS" not in os.environ:
            torch.set_num_threads(int(cpus))  # the task's CPUs, not the node's
        plan = load_plan(self.plan_source, self.overrides)
        planned = plan.cell(cell if isinstance(cell, str) else cell.id)
        if not isinstance(cell, str) and planned != cell:
            raise PlanError(f"{plan.source}: no cell {cell!r}")
        cell = planned
        state = StudyDir(self.out).cell_state(cell)
        job = os.environ.get("SLURM_ARRAY_JOB_ID", os.environ.get("SLURM_JOB_ID", "?"))
        task = os.environ.get("SLURM_ARRAY_TASK_ID")
        restarts = os.environ.get("SLURM_RESTART_COUNT", "0")
        print(f"{cell.id}: {'resuming' if state == 'partial' else 'training' if state == 'new' else 'finished'} "
              f"in Slurm job {job}{'_' + task if task else ''} (restart {restarts}), {torch.get_num_threads()} "
              "thread(s)", flush=True)
        return training.train_cell(plan, Path(self.out), cell)


def default_gpus(plan: Plan, out: Path, cells: list[Cell]) -> int:
    """GPUs per task when --gpus-per-cell is not given: 0 where every cell's config runs on the CPU, else 1."""
    runs = StudyDir(out).runs
    return 0 if all(plan.config(cell, runs).run.device == "cpu" for cell in cells) else 1


def submit_study(plan: Plan, out: Path, options: SlurmOptions, cells: list[Cell] | None = None,
                 reuse: list[Path] | None = None) -> int:
    """Submit the cells that are neither finished nor queued as one job array, one cell per task.

    Nothing is written and nothing submitted until submitit and Slurm's commands are found and ``sbatch --test-only``
    takes the options.

    Args:
        plan: the study plan.
        out: the study directory (on a file system the cluster's nodes share).
        options: the executor's options (`slurm_options`); with ``options.wait`` the tasks are followed (`follow`).
        cells: the cells to run (default: all of the plan).
        reuse: other study directories whose finished runs are copied in for the cells they already trained
            (`warpsense.study.reuse.reuse_cells`), before the rest is submitted.

    Returns:
        The exit code: 0 once submitted (or, with ``options.wait``, `follow`'s).

    Raises:
        ValueError: submitit or Slurm's commands missing, or options Slurm refuses (one line naming the option).
    """
    out = Path(out).absolute()
    study = StudyDir(out)
    all_cells = plan.cells()
    cells = all_cells if cells is None else cells
    require_slurm()
    finished = finished_runs(list(reuse or []))  # a bad --reuse directory is refused before anything is written
    queued = queued_cells(out, cells)
    if queued is None:
        raise ValueError("--executor slurm: squeue does not answer (is the Slurm controller up?)")
    todo = [cell for cell in cells if cell not in queued and study.cell_state(cell) != "done"]
    # a cell a local `study run` trains now: a task on another node would take its run directory over (the run lock
    # holds a pid, which that node cannot check). Only cells never submitted: a submitted cell's lock may be its
    # killed task's, a pid of another node that means nothing here
    submitted = latest_jobs(out)
    training = {cell: pid for cell in todo if cell.id not in submitted
                and (pid := study.run(cell).lock().holder()) is not None}
    if training:
        held = ", ".join(f"{cell.id} (process {pid})" for cell, pid in training.items())
        raise ValueError(f"--executor slurm: {len(training)} cell(s) are training on this machine now: {held}; "
                         "nothing submitted: let that run finish or stop it (Ctrl-C), then submit again")
    gpus = options.gpus_per_cell if options.gpus_per_cell is not None else default_gpus(plan, out, todo or cells)
    if todo:
        check_submission(options, gpus, len(todo))
    study.record_plan(plan)
    reused = reuse_cells(plan, out, todo, finished)
    todo = [cell for cell in todo if cell not in reused]
    numbering = {cell: all_cells.index(cell) + 1 for cell in cells}
    total = len(all_cells)
    for cell in cells:
        prefix = f"[{numbering[cell]}/{total}] {cell.id}"
        if cell in reused:
            print(f"{prefix}: the same training as {reused[cell]}, copied in", flush=True)
        elif cell in queued:
            print(f"{prefix}: queued or running as job {queued[cell]}, not submitted again", flush=True)
        elif cell not in todo:
            print(f"{prefix}: finished earlier, skipped", flush=True)
    if todo:
        # the longest cells first: Slurm starts an array's tasks by index, so with fewer nodes (or
        # --array-parallelism) than cells the short ones fill the end, as the local pool hands them out
        lengths = work.cell_work(plan, todo)
        array = submit(plan, out, sorted(todo, key=lambda cell: -lengths[cell]), options, gpus)
        resumed = sum(study.cell_state(cell) == "partial" for cell in todo)
        print(f"study: submitted {len(todo)} cell(s) ({resumed} resuming from a checkpoint) as Slurm job {array} "
              f"({_described(options, gpus)}); logs in {study.slurm}", flush=True)
    if options.wait:
        return follow(plan, out, cells)
    if todo or queued:
        print(f"study: the cells run on the cluster; follow them with: warpsense study status {shlex.quote(str(out))}")
    else:
        print(f"study finished; report: warpsense study report {shlex.quote(str(out))}")
    return 0


def submit(plan: Plan, out: Path, cells: list[Cell], options: SlurmOptions, gpus: int) -> str:
    """Submit ``cells`` as one job array through submitit (each task given its `Cell`) and record the tasks' ids in
    the study directory (`StudyDir.record_submission`); returns the array's job id."""
    import submitit
    from submitit.core.utils import FailedJobError, FailedSubmissionError

    study = StudyDir(out)
    executor = submitit.SlurmExecutor(folder=study.submitit)
    parameters = {"job_name": f"warpsense-{plan.name}", "time": options.time_minutes,
                  "array_parallelism": options.array_parallelism, "additional_parameters": dict(options.extra)}
    if options.partition:
        parameters["partition"] = options.partition
    if gpus:
        parameters["gpus_per_node"] = gpus
    executor.update_parameters(**parameters)
    task = CellTask(str(Path(plan.source).absolute()), plan.overrides, str(out))
    try:
        jobs = executor.map_array(task, list(cells))
    except (subprocess.CalledProcessError, FailedJobError, FailedSubmissionError) as error:
        output = getattr(error, "output", None) or getattr(error, "stderr", None) or str(error)
        output = output.decode(errors="replace") if isinstance(output, bytes) else str(output)
        raise ValueError(f"--executor slurm: sbatch refused the job array: {output.strip().splitlines()[-1]}") \
            from None
    array = jobs[0].job_id.split("_")[0]
    study.record_submission({
        "job_id": array, "submitted": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "sbatch": _sbatch_flags(options, gpus, len(cells)),
        "cells": {cell.id: job.job_id for cell, job in zip(cells, jobs)}})
    return array


def follow(plan: Plan, out: Path, cells: list[Cell], poll: float | None = None) -> int:
    """Follow the submitted cells of ``cells`` until each has finished or failed, one line per cell as it ends.

    Args:
        plan: the study plan.
        out: the study directory.
        cells: the cells to follow (those never submitted are passed over).
        poll: seconds between two looks at squeue (default: `POLL_SECONDS`).

    Returns:
        0 (all finished), 1 (some failed: the same command resumes them) or 130 (Ctrl-C: the tasks go on).
    """
    out = Path(out)
    study = StudyDir(out)
    all_cells = plan.cells()
    total = len(all_cells)
    jobs = latest_jobs(out)
    waiting = [cell for cell in cells if study.cell_state(cell) != "done" and cell.id in jobs]
    started, failed = time.perf_counter(), []
    try:
        while waiting:
            queue = slurm_status.queue_states()
            for cell in list(waiting):
                status = cell_status(out, cell, jobs[cell.id], queue)
                if status.state not in ("done", "failed"):
                    continue
                waiting.remove(cell)
                prefix = f"[{all_cells.index(cell) + 1}/{total}] {cell.id}"
                after = f"after {time.perf_counter() - started:.0f} s"
                if status.state == "done":
                    print(f"{prefix}: done {after} (job {jobs[cell.id]}), {status.detail}", flush=True)
                else:
                    failed.append(cell)
                    print(f"{prefix}: FAILED {after}: {status.detail}", file=sys.stderr, flush=True)
            if waiting:
                time.sleep(POLL_SECONDS if poll is None else poll)
    except KeyboardInterrupt:
        print(f"study: stopped following; the tasks go on (warpsense study status {out})", file=sys.stderr)
        return 130
    if failed:
        print(f"study: {len(failed)} of {total} cells failed: {', '.join(cell.id for cell in failed)}; run the same "
              "command again to resume them (finished cells are kept)", file=sys.stderr)
        return 1
    if all(study.cell_state(cell) == "done" for cell in cells):
        print(f"study finished; report: warpsense study report {out}")
    return 0
