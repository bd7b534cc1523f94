"""Running a study's cells: one ordinary run directory per cell under <out>/runs, resumable, going on past a failed
cell, in this process (CPU, or one cell) or as a local pool of processes over the GPUs (several cells per GPU).

A cell is finished when its run directory holds `warpsense.train.engine.EVALUATION` (written after the last epoch):
it is never trained again. A cell with a last checkpoint but no evaluation resumes from that checkpoint. A scheduler
of the user's (a Slurm job array, ...) runs the commands `--plan-only` prints; the report reads the same directory.
"""

from __future__ import annotations

import json
import os
import queue
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from warpsense.errors import first_line
from warpsense.files import write_json
from warpsense.study.plan import Cell, Plan, PlanError

PLAN_RECORD = "plan.json"
"""The resolved plan, written in the study directory by its first run (the report reads it)."""

THROUGHPUT = "throughput.json"
"""What each `study run` invocation trained, appended: cells finished, seconds, cells per hour, GPUs, per-cell
concurrency and the GPUs' busy fraction (sampled from nvidia-smi while it ran; absent without nvidia-smi)."""


def gpu_busy(gpus: list[str]) -> list[float] | None:
    """Busy percentage (0-100) of each GPU id now, from nvidia-smi; None where it cannot be read."""
    try:
        result = subprocess.run(["nvidia-smi", "--query-gpu=index,utilization.gpu", "--format=csv,noheader,nounits"],
                                capture_output=True, text=True, timeout=10, check=True)
        busy = dict(line.replace(" ", "").split(",")[:2] for line in result.stdout.strip().splitlines())
        return [float(busy[gpu]) for gpu in gpus]
    except (OSError, subprocess.SubprocessError, ValueError, KeyError):
        return None


class BusySampler:
    """Samples `gpu_busy` every ``interval`` seconds on a thread while a study runs; ``fractions()`` is each GPU's
    mean busy fraction in [0, 1] (None when nothing could be sampled)."""

    def __init__(self, gpus: list[str], interval: float = 2.0):
        self.gpus, self.interval, self.samples = gpus, interval, []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            sample = gpu_busy(self.gpus)
            if sample is None:
                return
            self.samples.append(sample)
            self._stop.wait(self.interval)

    def __enter__(self) -> "BusySampler":
        if self.gpus:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=15)

    def fractions(self) -> list[float] | None:
        if not self.samples:
            return None
        return [sum(sample[i] for sample in self.samples) / len(self.samples) / 100 for i in range(len(self.gpus))]


def record_throughput(out: Path, finished: int, seconds: float, gpus: list[str] | None, per_gpu: int,
                      busy: list[float] | None) -> dict:
    """Append this invocation's throughput to <out>/`THROUGHPUT` and print it in one line."""
    entry = {"cells_finished": finished, "seconds": seconds, "cells_per_hour": finished * 3600 / max(seconds, 1e-9),
             "gpus": list(gpus or []), "per_gpu": per_gpu if gpus else 1, "gpu_busy_fraction": busy}
    path = Path(out) / THROUGHPUT
    history = json.loads(path.read_text()) if path.is_file() else []
    write_json(path, history + [entry])
    print(f"study: {throughput_line(entry)}", flush=True)
    return entry


def throughput_line(entry: dict) -> str:
    """One `THROUGHPUT` entry in words (the run's last line, and the report's)."""
    where = f"{len(entry['gpus'])} GPU(s) x {entry['per_gpu']}" if entry["gpus"] else "one process"
    busy = entry.get("gpu_busy_fraction")
    busy_text = f"; GPU busy {', '.join(f'{fraction:.0%}' for fraction in busy)}" if busy else ""
    return (f"{entry['cells_finished']} cell(s) in {entry['seconds']:.0f} s on {where}: "
            f"{entry['cells_per_hour']:.1f} cells/hour{busy_text}")


def run_dir(out: Path, cell: Cell) -> Path:
    return Path(out) / "runs" / cell.run_name


def evaluation_path(out: Path, cell: Cell) -> Path:
    """The cell's `warpsense.train.engine.EVALUATION` file (present once the cell is finished)."""
    from warpsense.train.engine import EVALUATION

    return run_dir(out, cell) / EVALUATION


def read_evaluation(out: Path, cell: Cell) -> dict:
    return json.loads(evaluation_path(out, cell).read_text())


def cell_state(out: Path, cell: Cell) -> str:
    """"done" (evaluated), "partial" (a checkpoint to resume) or "new"."""
    from warpsense.train.run_dir import LAST

    if evaluation_path(out, cell).is_file():
        return "done"
    return "partial" if (run_dir(out, cell) / LAST).is_file() else "new"


def cell_command(plan: Plan, out: Path, cell: Cell) -> list[str]:
    """The command that runs one cell (what the local pool starts, and what `--plan-only` prints)."""
    command = ["warpsense", "study", "run", plan.source, "--out", str(out), "--cell", cell.id]
    for text in plan.overrides:
        command += ["--set", text]
    return command


def record_plan(plan: Plan, out: Path) -> None:
    """Write the plan into ``out`` (first run), or refuse a different plan for a study directory that has one."""
    out = Path(out)
    path = out / PLAN_RECORD
    record = {key: value for key, value in plan.to_dict().items() if key != "source"}
    if path.is_file():
        saved = json.loads(path.read_text())
        saved.pop("source", None)
        if saved != json.loads(json.dumps(record)):
            raise PlanError(f"{path}: this study directory holds another plan ({saved.get('name')!r} with other "
                            f"cameras, lights, seeds or overrides); use a new --out")
        return
    (out / "runs").mkdir(parents=True, exist_ok=True)  # shared by the cells' run folders
    write_json(path, {**record, "source": plan.source})


def train_cell(plan: Plan, out: Path, cell: Cell, progress: bool = False) -> dict:
    """Train (or resume) and evaluate one cell in this process; returns its evaluation record."""
    from warpsense.train.engine import train

    state = cell_state(out, cell)
    if state != "done":
        config = plan.config(cell, Path(out) / "runs")
        train(config, resume=run_dir(out, cell) if state == "partial" else False, progress=progress)
    return read_evaluation(out, cell)


def _score(record: dict) -> str:
    return ", ".join(f"{split} mIoU {metrics['miou']:.4f}" for split, metrics in record["splits"].items())


def run_cells(plan: Plan, out: Path, cells: list[Cell] | None = None, gpus: list[str] | None = None,
              per_gpu: int = 1, progress: bool = False, record: bool = True,
              sample_gpus: list[str] | None = None) -> int:
    """Run the cells not finished yet; a progress line per cell; returns the exit code (0 all finished, 1 some
    failed, 130 interrupted).

    Args:
        cells: the cells to run (default: all of the plan).
        gpus: device ids for a local pool of processes (CUDA_VISIBLE_DEVICES of each), ``per_gpu`` cells at once
            on each; None or empty: the cells run one after another in this process.
        record: append this invocation's throughput to <out>/`THROUGHPUT` (the pool's one-cell processes do not).
        sample_gpus: GPU ids whose busy fraction is sampled meanwhile (default: ``gpus``; the command passes the
            visible GPUs also when the cells run in this process on one GPU).
    """
    out = Path(out)
    cells = plan.cells() if cells is None else cells
    record_plan(plan, out)
    pending = [cell for cell in cells if cell_state(out, cell) != "done"]
    total = len(cells)
    for index, cell in enumerate(cells, start=1):
        if cell not in pending:
            print(f"[{index}/{total}] {cell.id}: finished earlier, skipped", flush=True)
    if not pending:
        return 0
    numbering = {cell: cells.index(cell) + 1 for cell in pending}
    started = time.perf_counter()
    sampled = list(sample_gpus if sample_gpus is not None else gpus or []) if record else []
    with BusySampler(sampled) as sampler:
        if gpus:
            failed = _pool(plan, out, pending, numbering, total, gpus, per_gpu)
        else:
            failed = _in_process(plan, out, pending, numbering, total, progress)
    if record:
        finished = sum(cell_state(out, cell) == "done" for cell in pending)
        record_throughput(out, finished, time.perf_counter() - started, gpus, per_gpu, sampler.fractions())
    if failed is None:
        return 130
    if failed:
        print(f"study: {len(failed)} of {total} cells failed: {', '.join(c.id for c in failed)}; the others are "
              f"done. Run the same command again to retry them.", file=sys.stderr)
        return 1
    return 0


def _in_process(plan, out, pending, numbering, total, progress) -> list[Cell] | None:
    """Cells one after another here; the failed ones, or None after Ctrl-C."""
    from warpsense.train.engine import TrainingInterrupted

    failed = []
    for cell in pending:
        started = time.perf_counter()
        prefix = f"[{numbering[cell]}/{total}] {cell.id}"
        print(f"{prefix}: {'resuming' if cell_state(out, cell) == 'partial' else 'training'}", flush=True)
        try:
            record = train_cell(plan, out, cell, progress)
        except TrainingInterrupted:
            print(f"{prefix}: interrupted; run the same command again to resume it (finished cells are kept)",
                  file=sys.stderr)
            return None
        except Exception as error:  # noqa: BLE001 - a failed cell is reported and the study goes on
            failed.append(cell)
            print(f"{prefix}: FAILED: {type(error).__name__}: {first_line(error)}", file=sys.stderr, flush=True)
            continue
        print(f"{prefix}: done in {time.perf_counter() - started:.0f} s, {_score(record)}", flush=True)
    return failed


def _pool(plan, out, pending, numbering, total, gpus, per_gpu) -> list[Cell] | None:
    """Cells as processes, ``per_gpu`` at once on each GPU; each writes its output to <out>/logs/<cell>.log. The
    failed cells, or None after Ctrl-C (every running cell is interrupted; its last checkpoint resumes it)."""
    slots: queue.Queue = queue.Queue()
    for gpu in gpus:
        for _ in range(per_gpu):
            slots.put(gpu)
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    failed, running, lock, stopping = [], set(), threading.Lock(), threading.Event()

    def work(cell: Cell) -> None:
        gpu = slots.get()
        prefix = f"[{numbering[cell]}/{total}] {cell.id}"
        try:
            if stopping.is_set():
                return
            log = logs / f"{cell.run_name}.log"
            print(f"{prefix}: started on GPU {gpu} (log {log})", flush=True)
            started = time.perf_counter()
            with open(log, "a") as handle:
                process = subprocess.Popen([sys.executable, "-m", *cell_command(plan, out, cell)], stdout=handle,
                                           stderr=subprocess.STDOUT, env={**os.environ, "CUDA_VISIBLE_DEVICES": gpu})
                with lock:
                    running.add(process)
                code = process.wait()
                with lock:
                    running.discard(process)
            if stopping.is_set():
                return
            elapsed = time.perf_counter() - started
            if code == 0 and cell_state(out, cell) == "done":
                record = read_evaluation(out, cell)
                print(f"{prefix}: done in {elapsed:.0f} s on GPU {gpu}, {_score(record)}", flush=True)
                return
            lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
            with lock:
                failed.append(cell)
            print(f"{prefix}: FAILED (exit {code}): {lines[-1] if lines else 'no output'}", file=sys.stderr,
                  flush=True)
        finally:
            slots.put(gpu)

    threads = [threading.Thread(target=work, args=(cell,), daemon=True) for cell in pending]
    for thread in threads:  # each thread waits for a free GPU slot, so at most len(gpus) * per_gpu run at once
        thread.start()
    try:
        for thread in threads:
            while thread.is_alive():
                thread.join(timeout=1.0)
    except KeyboardInterrupt:
        stopping.set()
        with lock:
            processes = list(running)
        for process in processes:  # each cell stops at once and keeps its last epoch's checkpoint
            process.send_signal(signal.SIGINT)
        for process in processes:
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
        print("study: interrupted; run the same command again to resume (finished cells are kept)", file=sys.stderr)
        return None
    return sorted(failed, key=lambda cell: numbering[cell])


def plan_commands(plan: Plan, out: Path) -> list[str]:
    """One shell command per cell, for a scheduler of the user's."""
    return [shlex.join(cell_command(plan, out, cell)) for cell in plan.cells()]
