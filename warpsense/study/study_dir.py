"""A study's directory: the files in it and how each is read and written (`StudyDir`, the one place that names
them). Each cell is an ordinary run directory under runs/ (`warpsense.train.run_dir.RunDir` owns its files); the
thin functions below (``run_dir(out, cell)``, ``cell_state(out, cell)``, ...) are `StudyDir`'s methods for callers
that hold a study directory's path."""

from __future__ import annotations

import contextlib
import json
import math
import sys
from pathlib import Path

from warpsense.errors import first_line
from warpsense.files import Folder, atomic_write, write_json
from warpsense.study.plan import Cell, Plan, PlanError
from warpsense.train.run_dir import RunDir


class StudyDir(Folder):
    """A study directory: the one owner of its files' names and of how each is read and written.

    Files: `PLAN` (the resolved plan, written by the study's first run; `record_plan`), `RUNS`/<cell> (each cell's
    run directory, a `RunDir`: its config, metrics, checkpoints and evaluation), `LOGS`/<cell>.log (a pool worker's
    output for the cell) and <cell>.failed (why its last local run failed, for `warpsense study status`),
    `THROUGHPUT` (what each `study run` invocation trained), `JOBS` and `SUBMITIT` (the Slurm executor's
    submissions and submitit's folders) and `SEARCH` (a [[search]]'s designs, `warpsense.study.search`). Readers of
    damaged files raise one-line PlanErrors naming the file and field (`read_record`); writers write atomically.

    Args:
        path: the study directory (it need not exist yet).
    """

    PLAN = "plan.json"
    RUNS = "runs"
    LOGS = "logs"
    THROUGHPUT = "throughput.json"
    """What each `study run` invocation trained, appended: cells finished, seconds, cells per hour, GPUs, per-cell
    concurrency and the GPUs' busy fraction (sampled from nvidia-smi while it ran; absent without nvidia-smi)."""
    SLURM = "slurm"
    JOBS = "slurm/jobs.json"
    """The record of its Slurm submissions: each one's array job id and the task id of every cell."""
    SUBMITIT = "slurm/%j"
    """submitit's folder of each task (its sbatch script, pickles and logs)."""
    SEARCH = "search.json"

    # --- where each file is ------------------------------------------------------------------------------------

    @property
    def plan(self) -> Path:
        return self.path / self.PLAN

    @property
    def runs(self) -> Path:
        return self.path / self.RUNS

    @property
    def logs(self) -> Path:
        return self.path / self.LOGS

    @property
    def throughput(self) -> Path:
        return self.path / self.THROUGHPUT

    @property
    def slurm(self) -> Path:
        return self.path / self.SLURM

    @property
    def jobs(self) -> Path:
        return self.path / self.JOBS

    @property
    def submitit(self) -> Path:
        return self.path / self.SUBMITIT

    @property
    def search(self) -> Path:
        return self.path / self.SEARCH

    def run(self, cell: Cell) -> RunDir:
        """The run directory of ``cell`` (runs/<cell.run_name>)."""
        return RunDir(self.runs / cell.run_name)

    def log(self, cell: Cell) -> Path:
        """Where a pool worker appends the output of ``cell`` (logs/<cell>.log)."""
        return self.logs / f"{cell.run_name}.log"

    def failure(self, cell: Cell) -> Path:
        """Where a local run records why ``cell`` failed (logs/<cell>.failed, one line), for `warpsense study
        status`; removed when the cell trains again."""
        return self.logs / f"{cell.run_name}.failed"

    # --- cells ---------------------------------------------------------------------------------------------------

    def cell_state(self, cell: Cell) -> str:
        """"done" (evaluated), "partial" (a checkpoint to resume) or "new"."""
        run = self.run(cell)
        if run.finished():
            return "done"
        return "partial" if run.resumable() else "new"

    def read_evaluation(self, cell: Cell) -> dict:
        """The evaluation of a finished cell (`RunDir.EVALUATION`); a one-line PlanError naming it otherwise."""
        return read_record(self.run(cell).evaluation)

    def record_failure(self, cell: Cell, reason: str) -> None:
        """Record why ``cell`` failed (`failure`), best effort: a record that cannot be written (a full disk) must
        not stop the study, which has reported the failure already."""
        path = self.failure(cell)
        with contextlib.suppress(OSError):
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(path) as temporary:
                temporary.write_text(reason.replace("\n", " ") + "\n")

    def recorded_failure(self, cell: Cell) -> str | None:
        """Why ``cell``'s last local run failed (`record_failure`), or None."""
        try:
            return self.failure(cell).read_text().strip() or None
        except OSError:
            return None

    def clear_failure(self, cell: Cell) -> None:
        """Forget ``cell``'s recorded failure: it trains again."""
        self.failure(cell).unlink(missing_ok=True)

    # --- the plan ------------------------------------------------------------------------------------------------

    def read_plan(self) -> dict:
        """The plan the directory holds (`PLAN`, as `record_plan` wrote it); a one-line PlanError naming the
        directory where it holds none, or the file where it is unreadable or not a plan."""
        if not self.path.is_dir():
            raise PlanError(f"{self.path}: no such study directory")
        if not self.plan.is_file():
            raise PlanError(f"{self.path}: not a study directory (no {self.PLAN}); run `warpsense study run PLAN "
                            f"--out {self.path}` first")
        record = read_record(self.plan)
        try:
            Plan.from_dict(record)
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            raise PlanError(f"{self.plan}: not a study plan record ({type(error).__name__}: {error})") from None
        return record

    def record_plan(self, plan: Plan) -> None:
        """Write ``plan`` into the directory (first run), or refuse a different plan for a directory that has
        one."""
        record = {key: value for key, value in plan.to_dict().items() if key != "source"}
        if self.plan.is_file():
            saved = self.read_plan()
            saved.pop("source", None)
            saved.setdefault("folds", "none")  # a plan recorded before studies had folds
            saved.setdefault("sequences", [])
            if saved != json.loads(json.dumps(record)):
                raise PlanError(f"{self.plan}: this study directory holds another plan ({saved.get('name')!r} with "
                                "other cameras, lights, seeds or overrides); use a new --out")
            return
        self.runs.mkdir(parents=True, exist_ok=True)  # shared by the cells' run folders
        write_json(self.plan, {**record, "source": plan.source})

    # --- throughput ----------------------------------------------------------------------------------------------

    def read_throughput(self) -> list[dict]:
        """The entries of `THROUGHPUT` (none where it is absent), each checked for the fields `throughput_line`
        reads: a one-line PlanError naming the file, entry and field otherwise."""
        path = self.throughput
        if not path.is_file():
            return []
        entries = read_record(path, list)
        for number, entry in enumerate(entries, start=1):
            if not isinstance(entry, dict):
                raise PlanError(f"{path}: entry {number}: expected a JSON object, got {type(entry).__name__}")
            for field, kind in THROUGHPUT_FIELDS.items():
                value = entry.get(field)
                right = _finite_number(value) if kind is float else \
                    isinstance(value, kind) and not isinstance(value, bool)
                if not right:
                    expected = "a finite number" if kind is float else kind.__name__
                    raise PlanError(f"{path}: entry {number}: {field}: expected {expected}, got {value!r}")
            busy = entry.get("gpu_busy_fraction")
            if busy is not None and not (isinstance(busy, list) and all(_finite_number(value) for value in busy)):
                raise PlanError(f"{path}: entry {number}: gpu_busy_fraction: expected null or a list of numbers, "
                                f"got {busy!r}")
        return entries

    def append_throughput(self, entry: dict) -> None:
        """Add an invocation's entry to `THROUGHPUT`; a damaged history costs this entry (a warning), not the
        study."""
        try:
            history = self.read_throughput()
        except ValueError as error:  # the cells are trained: a damaged history costs this entry, not the study
            print(f"study: warning: {error}; this run's throughput is not recorded there", file=sys.stderr,
                  flush=True)
            return
        write_json(self.throughput, history + [entry])

    # --- Slurm ---------------------------------------------------------------------------------------------------

    def read_jobs(self) -> list[dict]:
        """Its Slurm submissions (`JOBS`), oldest first; a one-line PlanError naming the file and field where it is
        damaged (each submission: its array's job_id and the task id of every cell)."""
        path = self.jobs
        if not path.is_file():
            return []
        submissions = read_record(path, dict).get("submissions")
        if not isinstance(submissions, list):
            raise PlanError(f"{path}: submissions: expected a list of Slurm submissions, got {submissions!r}")
        for number, submission in enumerate(submissions, start=1):
            cells = submission.get("cells") if isinstance(submission, dict) else None
            if not isinstance(cells, dict) or not all(isinstance(task, str) for task in cells.values()):
                raise PlanError(f"{path}: submission {number}: cells: expected an object of cell -> task id, got "
                                f"{cells!r}")
            if not isinstance(submission.get("job_id"), str):
                raise PlanError(f"{path}: submission {number}: job_id: expected a job id, got "
                                f"{submission.get('job_id')!r}")
        return submissions

    def record_submission(self, submission: dict) -> None:
        """Add a Slurm submission (its job_id and every cell's task id) to `JOBS`."""
        submissions = self.read_jobs() + [submission]
        self.jobs.parent.mkdir(parents=True, exist_ok=True)
        write_json(self.jobs, {"submissions": submissions})


THROUGHPUT_FIELDS = {"cells_finished": int, "seconds": float, "cells_per_hour": float, "gpus": list, "per_gpu": int}
"""The fields of a `StudyDir.THROUGHPUT` entry that its line (`throughput_line`) reads, and their types."""


def read_record(path: Path, kind: type | None = None):
    """The JSON file ``path`` of a study directory (its plan, throughput, a cell's evaluation, a run's config, the
    Slurm jobs); where it cannot be read or parsed, or (with ``kind``, dict or list) holds another JSON type, a
    one-line PlanError naming it (json's own message names no file)."""
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, ValueError, RecursionError) as error:  # ValueError: JSONDecodeError, UnicodeDecodeError
        raise PlanError(f"{path}: unreadable: {first_line(error)}") from None
    if kind is not None and not isinstance(record, kind):
        expected = "a JSON object" if kind is dict else "a JSON list"
        raise PlanError(f"{path}: unreadable: expected {expected}, got {type(record).__name__}")
    return record


def _finite_number(value) -> bool:
    """Whether a JSON value is a finite number (not a bool, whose JSON is true / false)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def throughput_line(entry: dict) -> str:
    """One `StudyDir.THROUGHPUT` entry in words (the run's last line, and the report's)."""
    where = f"{len(entry['gpus'])} GPU(s) x {entry['per_gpu']}" if entry["gpus"] else "one process"
    where += " under MPS" if entry.get("mps") else ""
    busy = entry.get("gpu_busy_fraction")
    busy_text = f"; GPU busy {', '.join(f'{fraction:.0%}' for fraction in busy)}" if busy else ""
    return (f"{entry['cells_finished']} cell(s) in {entry['seconds']:.0f} s on {where}: "
            f"{entry['cells_per_hour']:.1f} cells/hour{busy_text}")


def record_throughput(out: Path, finished: int, seconds: float, gpus: list[str] | None, per_gpu: int,
                      busy: list[float] | None, mps: bool = False) -> dict:
    """Append this invocation's throughput to <out>/`StudyDir.THROUGHPUT` and print it in one line."""
    entry = {"cells_finished": finished, "seconds": seconds, "cells_per_hour": finished * 3600 / max(seconds, 1e-9),
             "gpus": list(gpus or []), "per_gpu": per_gpu if gpus else 1, "gpu_busy_fraction": busy, "mps": mps}
    print(f"study: {throughput_line(entry)}", flush=True)
    StudyDir(out).append_throughput(entry)
    return entry


# --- `StudyDir`'s methods for callers that hold the directory's path -----------------------------------------------

def run_dir(out: Path, cell: Cell) -> Path:
    """The run directory of ``cell`` (`StudyDir.run`)."""
    return StudyDir(out).run(cell).path


def evaluation_path(out: Path, cell: Cell) -> Path:
    """The cell's `RunDir.EVALUATION` file (present once the cell is finished)."""
    return StudyDir(out).run(cell).evaluation


def read_evaluation(out: Path, cell: Cell) -> dict:
    return StudyDir(out).read_evaluation(cell)


def cell_state(out: Path, cell: Cell) -> str:
    """`StudyDir.cell_state`: "done", "partial" or "new"."""
    return StudyDir(out).cell_state(cell)


def failure_path(out: Path, cell: Cell) -> Path:
    return StudyDir(out).failure(cell)


def record_failure(out: Path, cell: Cell, reason: str) -> None:
    StudyDir(out).record_failure(cell, reason)


def recorded_failure(out: Path, cell: Cell) -> str | None:
    return StudyDir(out).recorded_failure(cell)


def read_plan_record(study_dir: Path) -> dict:
    return StudyDir(study_dir).read_plan()


def record_plan(plan: Plan, out: Path) -> None:
    StudyDir(out).record_plan(plan)
