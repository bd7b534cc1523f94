"""The local pool: a study's cells on worker processes over the GPUs (`warpsense.study.worker`), several per GPU,
the longest cells first and each GPU's work balanced (`CellPool`)."""

from __future__ import annotations

import collections
import contextlib
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from warpsense.errors import first_line
from warpsense.study import work, worker
from warpsense.study.plan import Cell, Plan
from warpsense.study.study_dir import StudyDir
from warpsense.study.training import score_line


class CellPool:
    """Cells on ``per_gpu`` worker processes per GPU (`warpsense.study.worker.cell_worker`), the longest first
    (`warpsense.study.work.cell_work`; equal ones in plan order), each slot taking the next pending cell when it is
    free and no GPU with a free slot runs less work than its own (fewer cells than slots spread over the GPUs
    instead of filling the first, and a GPU's cells under MPS share it, so its load is the sum of their work); each
    cell writes its output to its log (`StudyDir.log`). A worker that dies fails its cell and is replaced for the
    next.

    Why longest first by work: the 12 cells of 3 CamVid folds x 4 seeds on 4 GPUs x 3 slots went out in plan order,
    and one GPU took the three longest cells (406 training frames each) while two others sat idle for a third of the
    study or more (docs/benchmarks.md, studies per GPU-hour).

    Args:
        plan: the study plan.
        out: the study directory.
        pending: the cells to train.
        numbering: each cell's number in the study's progress lines ("[3/12]"), of ``total``.
        gpus: the pool's GPU ids (`warpsense.study.gpus.cuda_device`).
        per_gpu: worker processes on each GPU.
        environment: extra environment of the workers (the pool's MPS daemon: `warpsense.study.mps`).
        progress: each cell's progress bars into its log.
    """

    def __init__(self, plan: Plan, out: Path, pending: list[Cell], numbering: dict[Cell, int], total: int,
                 gpus: list[str], per_gpu: int, environment: dict[str, str] | None = None, progress: bool = False):
        self.plan, self.study, self.numbering, self.total = plan, StudyDir(out), numbering, total
        self.gpus, self.per_gpu, self.environment, self.progress = gpus, per_gpu, environment, progress
        self.work = work.cell_work(plan, pending)
        self.todo = collections.deque(sorted(pending, key=lambda cell: -self.work[cell]))  # stable: ties in order
        self.failed: list[Cell] = []
        self.running: set[subprocess.Popen] = set()
        self.lock, self.stopping = threading.Lock(), threading.Event()
        self.turn = threading.Condition()  # guards `todo`, `active` and `load`
        self.active = dict.fromkeys(gpus, 0)  # cells running on each GPU
        self.load = dict.fromkeys(gpus, 0)  # their work

    def run(self) -> list[Cell] | None:
        """Train the cells; the failed ones, or None after Ctrl-C (every worker is interrupted; a cell's last
        checkpoint resumes it)."""
        self.study.logs.mkdir(parents=True, exist_ok=True)
        threads = [threading.Thread(target=self._slot, args=(gpu,), daemon=True)
                   for gpu in self.gpus for _ in range(self.per_gpu)]
        for thread in threads:
            thread.start()
        try:
            for thread in threads:
                while thread.is_alive():
                    thread.join(timeout=1.0)
        except KeyboardInterrupt:
            self._interrupt()
            print("study: interrupted; run the same command again to resume (finished cells are kept)",
                  file=sys.stderr)
            return None
        return sorted(self.failed, key=lambda cell: self.numbering[cell])

    def _interrupt(self) -> None:
        """Ctrl-C: each worker's cell stops at once and keeps its last epoch's checkpoint."""
        self.stopping.set()
        with self.lock:
            processes = list(self.running)
        for process in processes:
            process.send_signal(signal.SIGINT)
        for process in processes:
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()

    # --- handing out the cells ---------------------------------------------------------------------------------

    def _take(self, gpu: str) -> Cell | None:
        """The next pending cell for a slot of ``gpu`` once no GPU with a free slot runs less work; None when none
        is left."""
        with self.turn:
            while self.todo and not self.stopping.is_set() and any(
                    self.active[other] < self.per_gpu and self.load[other] < self.load[gpu] for other in self.gpus):
                self.turn.wait(timeout=1.0)
            if not self.todo or self.stopping.is_set():
                return None
            cell = self.todo.popleft()
            self.active[gpu] += 1
            self.load[gpu] += self.work[cell]
            self.turn.notify_all()  # a slot of another GPU may wait for this one to take its share
            return cell

    def _release(self, gpu: str, cell: Cell) -> None:
        with self.turn:
            self.active[gpu] -= 1
            self.load[gpu] -= self.work[cell]
            self.turn.notify_all()

    def _slot(self, gpu: str) -> None:
        """One worker slot of ``gpu``: its cells one after another on one worker process."""
        process = None
        while (cell := self._take(gpu)) is not None:
            try:
                process = self._train(gpu, cell, process)
            except Exception as error:  # e.g. the worker cannot start: the cell fails, the slot goes on
                if process is not None:
                    self._stop(process)
                process = None
                self._fail(cell, first_line(error))
            finally:
                self._release(gpu, cell)
        if process is not None and not self.stopping.is_set():
            self._stop(process)

    # --- the workers ---------------------------------------------------------------------------------------------

    def _start(self, gpu: str) -> subprocess.Popen:
        environment = worker.worker_environment(gpu, len(self.gpus) * self.per_gpu, extra=self.environment)
        process = subprocess.Popen(worker.worker_command(self.plan, self.study.path, self.progress),
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1,
                                   env=environment)
        with self.lock:
            self.running.add(process)
        return process

    def _stop(self, process: subprocess.Popen) -> None:
        with contextlib.suppress(OSError):
            process.stdin.close()
        process.wait()
        with self.lock:
            self.running.discard(process)

    def _train(self, gpu: str, cell: Cell, process: subprocess.Popen | None) -> subprocess.Popen | None:
        """Train ``cell`` on the slot's worker ``process`` (a fresh one when None); the worker for its next
        cell."""
        prefix = f"[{self.numbering[cell]}/{self.total}] {cell.id}"
        log = self.study.log(cell)
        print(f"{prefix}: started on GPU {gpu} (log {log})", flush=True)
        self.study.clear_failure(cell)
        started = time.perf_counter()
        process = process or self._start(gpu)
        try:
            process.stdin.write(worker.cell_line(cell) + "\n")
            process.stdin.flush()
            text = process.stdout.readline().strip()
        except OSError:
            text = ""
        if self.stopping.is_set():
            return process
        answer = worker.Answer.parse(text)
        if answer is not None and answer.done and answer.cell == cell and self.study.cell_state(cell) == "done":
            record = self.study.read_evaluation(cell)
            print(f"{prefix}: done in {time.perf_counter() - started:.0f} s on GPU {gpu}, {score_line(record)}",
                  flush=True)
            return process
        if not text:  # the worker died: its exit status, and a fresh worker for the next cell
            self._stop(process)
            reason = f"worker exit {process.returncode}"
            process = None
        elif answer is None:
            reason = f"the worker's answer is not one: {text[:200]!r}"
        elif answer.cell != cell:
            reason = f"the worker answered for another cell ({answer.reason or 'done'})"
        elif answer.done:
            reason = "the worker answered done, yet the cell holds no evaluation"
        else:
            reason = answer.reason  # the worker's own line: "Type: message"
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()] \
            if log.is_file() else []
        detail = lines[-1] if lines else "no output"
        self._fail(cell, reason, None if detail == reason else detail)
        return process

    def _fail(self, cell: Cell, why: str, detail: str | None = None) -> None:
        """Record ``cell`` as failed and say so: "FAILED (why)", then ": detail" where given."""
        with self.lock:
            self.failed.append(cell)
        more = f": {detail}" if detail else ""
        self.study.record_failure(cell, why + more)
        print(f"[{self.numbering[cell]}/{self.total}] {cell.id}: FAILED ({why}){more}", file=sys.stderr, flush=True)
