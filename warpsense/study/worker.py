"""A worker of the local pool (`warpsense.study.pool`): one process per GPU slot that trains the cells the pool
sends it, one after another, and answers each. The command and environment that start it, and its protocol on
stdin and stdout: one JSON object a line each way, a cell as its typed fields (`cell_line`, `read_cell`) and an
answer as an `Answer`, so that a cell reaches the worker as the plan made it (its seed an integer throughout) and a
line that is not one is a failure named, never a crash or a cell mistaken for another."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import sys
import traceback
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from warpsense.errors import first_line
from warpsense.study import training
from warpsense.study.command_lines import study_command
from warpsense.study.gpus import cuda_device
from warpsense.study.plan import Cell, Plan, PlanError
from warpsense.study.study_dir import StudyDir

CELL_FIELDS = {"camera": str, "light": str, "seed": int, "fold": str}
"""A cell's fields on the wire (`Cell`'s) and their JSON types."""


def cell_line(cell: Cell) -> str:
    """``cell`` as one line of the protocol: its fields as a JSON object (no newline)."""
    return json.dumps(dataclasses.asdict(cell))


def read_cell(plan: Plan, line: str) -> Cell:
    """The cell of ``plan`` a protocol line (`cell_line`) names; a one-line PlanError quoting the line where it is
    not a JSON object of `CELL_FIELDS` with their types, or names no cell of the plan (a design of a [[search]] is
    one: `Plan.cell`)."""
    try:
        fields = json.loads(line)
    except (ValueError, RecursionError):
        fields = None
    typed = isinstance(fields, dict) and set(fields) == set(CELL_FIELDS) and all(
        isinstance(fields[name], kind) and not isinstance(fields[name], bool) for name, kind in CELL_FIELDS.items())
    if not typed:
        raise PlanError(f"not a cell of the pool's protocol (a JSON object of {', '.join(CELL_FIELDS)}): "
                        f"{line.strip()[:200]!r}")
    cell = Cell(**fields)
    if plan.cell(cell.id) != cell:  # an id that reads as another cell's (a fold named like a seed)
        raise PlanError(f"{plan.source}: no cell {cell!r}")
    return cell


@dataclass(frozen=True)
class Answer:
    """A worker's answer for a cell: ``done``, or failed with ``reason`` ("Type: message"); ``cell`` None where the
    line it answers named no cell."""

    cell: Cell | None
    done: bool
    reason: str = ""

    def line(self) -> str:
        """The answer as one line of the protocol (no newline)."""
        cell = None if self.cell is None else dataclasses.asdict(self.cell)
        return json.dumps({"cell": cell, "done": self.done, "reason": self.reason})

    @classmethod
    def parse(cls, line: str) -> "Answer | None":
        """The answer a line holds (`line`); None where it holds none (a worker's stray output)."""
        try:
            record = json.loads(line)
            cell = record["cell"]
            answer = cls(None if cell is None else Cell(**cell), record["done"], record["reason"])
        except (ValueError, RecursionError, TypeError, KeyError):
            return None
        return answer if isinstance(answer.done, bool) and isinstance(answer.reason, str) else None


def worker_command(plan: Plan, out: Path, progress: bool = False) -> list[str]:
    """The command of one of the local pool's worker processes (`cell_worker`), with ``progress`` bars."""
    return [sys.executable, "-m", *study_command(plan, out, "--worker", *(["--progress"] if progress else []))]


@contextlib.contextmanager
def _output_to(handle) -> Iterator[None]:
    """Python's stdout and stderr, and file descriptors 1 and 2 (native libraries' output), into ``handle``, then
    back."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    os.dup2(handle.fileno(), 1)
    os.dup2(handle.fileno(), 2)
    try:
        with contextlib.redirect_stdout(handle), contextlib.redirect_stderr(handle):
            yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])


def cell_worker(plan: Plan, out: Path, progress: bool = False) -> int:
    """One process of the local pool: trains the cells that arrive on stdin (`cell_line`, one a line), one after
    another in this process, each one's output (with ``progress``: its progress bars too) appended to its log
    (`StudyDir.log`), and answers each on stdout with one line (`Answer`): done, or failed with the reason. One
    process per GPU slot rather than one per cell: the interpreter, CUDA context, Warp modules and the data on the
    device are paid once per worker (a process per cell took a short cell several times as long as one process
    training them in turn). Returns 0 at the end of stdin, 130 on Ctrl-C."""
    from warpsense.train.engine import TrainingInterrupted

    study = StudyDir(out)
    answers = os.fdopen(os.dup(1), "w", buffering=1)
    sys.stdout.flush()
    os.dup2(2, 1)  # anything printed between cells goes to stderr: stdout carries the answers alone
    for line in sys.stdin:
        if not line.strip():
            continue
        try:
            cell = read_cell(plan, line)
        except PlanError as error:  # the pool's line names no cell: said, and the worker goes on
            answers.write(Answer(None, False, f"{type(error).__name__}: {first_line(error)}").line() + "\n")
            continue
        with open(study.log(cell), "a", buffering=1) as handle, _output_to(handle):
            try:
                state = study.cell_state(cell)
                print(f"{cell.id}: {'resuming' if state == 'partial' else 'training'} in worker process "
                      f"{os.getpid()}", flush=True)
                training.train_cell(plan, study.path, cell, progress)
                answer = Answer(cell, True)
            except TrainingInterrupted:
                return 130
            except Exception as error:  # noqa: BLE001 - a failed cell is reported and the worker goes on
                traceback.print_exc()
                answer = Answer(cell, False, f"{type(error).__name__}: {first_line(error)}")
        answers.write(answer.line() + "\n")
    return 0


def worker_environment(gpu: str, workers: int, environ=None, cores: int | None = None,
                       extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of a pool worker: its GPU alone (``CUDA_VISIBLE_DEVICES``) and its share of the CPU's cores
    as OpenMP threads (``OMP_NUM_THREADS`` = cores // workers, at least 1; kept where the caller set it), as
    torchrun limits its ranks: every worker running an OpenMP pool of all the cores oversubscribes the CPU, and each
    cell's set-up (the data onto the GPU, its copy-paste classes) took several times as long.

    The GPU is ``gpu``'s entry of the caller's CUDA_VISIBLE_DEVICES (`warpsense.study.gpus.cuda_device`). Under the
    pool's MPS daemon (``extra`` names its pipe directory) it stays the bare id: the daemon, started with the caller's
    environment, renumbers the devices it sees from 0, and a client naming one by its outer index fails (NVIDIA's
    MPS guide, CUDA_VISIBLE_DEVICES)."""
    environment = dict(os.environ if environ is None else environ)
    device = cuda_device(gpu, environment)  # an id past the visible devices is refused either way
    environment["CUDA_VISIBLE_DEVICES"] = gpu if "CUDA_MPS_PIPE_DIRECTORY" in (extra or {}) else device
    cores = cores or os.cpu_count() or 1
    environment.setdefault("OMP_NUM_THREADS", str(max(1, cores // max(workers, 1))))
    environment.update(extra or {})  # the pool's MPS daemon (warpsense.study.mps)
    return environment
