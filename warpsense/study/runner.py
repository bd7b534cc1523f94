"""Running a study's cells: one ordinary run directory per cell in the study directory (`StudyDir`), resumable,
going on past a failed cell, in this process (CPU, or one cell) or on a local pool of worker processes over the GPUs
(several per GPU: `warpsense.study.pool`).

A cell is finished when its run directory holds its evaluation (`RunDir.EVALUATION`, written after the last epoch):
it is never trained again. A cell with a last checkpoint but no evaluation resumes from that checkpoint. A scheduler
of the user's (a Slurm job array, ...) runs the commands `--plan-only` prints (`warpsense.study.command_lines`); the
report reads the same directory.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from warpsense.errors import first_line
from warpsense.study import training
from warpsense.study.gpus import BusySampler
from warpsense.study.mps import mps_daemon
from warpsense.study.mps import wanted as mps_wanted
from warpsense.study.plan import Cell, Plan
from warpsense.study.pool import CellPool
from warpsense.study.reuse import finished_runs, reuse_cells
from warpsense.study.study_dir import StudyDir, record_throughput
from warpsense.study.training import score_line


def run_cells(plan: Plan, out: Path, cells: list[Cell] | None = None, gpus: list[str] | None = None,
              per_gpu: int = 1, progress: bool = False, record: bool = True,
              sample_gpus: list[str] | None = None, reuse: list[Path] | None = None, mps: str = "auto") -> int:
    """Run the cells not finished yet; a progress line per cell; returns the exit code (0 all finished, 1 some
    failed, 130 interrupted).

    Args:
        cells: the cells to run (default: all of the plan).
        progress: each cell's progress bars: on this process's output where the cells run here, in each cell's log
            with a pool (several workers' bars would overwrite each other on one terminal).
        gpus: device ids for a local pool of worker processes (indices into CUDA_VISIBLE_DEVICES:
            `warpsense.study.gpus.cuda_device`), ``per_gpu`` on each, each training its cells one after another;
            None or empty: the cells run one after another here.
        record: append this invocation's throughput to the study directory's (`StudyDir.THROUGHPUT`; a one-cell
            invocation does not).
        sample_gpus: GPU ids whose busy fraction is sampled meanwhile (default: ``gpus``; the command passes the
            visible GPUs also when the cells run in this process on one GPU).
        reuse: other study directories whose finished runs are copied in for the cells they already trained
            (`warpsense.study.reuse.reuse_cells`).
        mps: run the pool's workers under a CUDA MPS daemon of its own (`warpsense.study.mps`): "auto" (with
            ``per_gpu`` > 1 where the control program is on the PATH), "on" or "off".
    """
    out = Path(out)
    study = StudyDir(out)
    cells = plan.cells() if cells is None else cells
    shared = bool(gpus) and mps_wanted(mps, per_gpu)  # a bad mode, or "on" without MPS, before anything is written
    finished = finished_runs(list(reuse or []))  # a bad directory is refused before anything is written
    study.record_plan(plan)
    reused = reuse_cells(plan, out, cells, finished)
    pending = [cell for cell in cells if study.cell_state(cell) != "done"]
    total = len(cells)
    for index, cell in enumerate(cells, start=1):
        if cell in reused:
            print(f"[{index}/{total}] {cell.id}: the same training as {reused[cell]}, copied in", flush=True)
        elif cell not in pending:
            print(f"[{index}/{total}] {cell.id}: finished earlier, skipped", flush=True)
    if not pending:
        return 0
    numbering = {cell: cells.index(cell) + 1 for cell in pending}
    started = time.perf_counter()
    sampled = list(sample_gpus if sample_gpus is not None else gpus or []) if record else []
    with BusySampler(sampled) as sampler:
        if gpus:
            if progress:
                print(f"study: --progress: each cell's progress bars go to its log ({study.logs}/<cell>.log)",
                      flush=True)
            with mps_daemon(shared) as environment:
                failed = CellPool(plan, out, pending, numbering, total, gpus, per_gpu, environment, progress).run()
        else:
            failed = _in_process(plan, out, pending, numbering, total, progress)
    if record:
        finished = sum(study.cell_state(cell) == "done" for cell in pending)
        record_throughput(out, finished, time.perf_counter() - started, gpus, per_gpu, sampler.fractions(), shared)
    if failed is None:
        return 130
    if failed:
        resumed = [str(study.run(cell)) for cell in failed if study.cell_state(cell) == "partial"]
        again = (f" A retry resumes {', '.join(resumed)} from its last checkpoint: if it fails the same way, delete "
                 "that folder to train the cell from the start.") if resumed else ""
        print(f"study: {len(failed)} of {total} cells failed: {', '.join(c.id for c in failed)}; the others are "
              f"done. Run the same command again to retry them.{again}", file=sys.stderr)
        return 1
    return 0


def _in_process(plan, out, pending, numbering, total, progress) -> list[Cell] | None:
    """Cells one after another here; the failed ones, or None after Ctrl-C."""
    from warpsense.train.engine import TrainingInterrupted

    study = StudyDir(out)
    failed = []
    for cell in pending:
        started = time.perf_counter()
        prefix = f"[{numbering[cell]}/{total}] {cell.id}"
        print(f"{prefix}: {'resuming' if study.cell_state(cell) == 'partial' else 'training'}", flush=True)
        study.clear_failure(cell)
        try:
            record = training.train_cell(plan, out, cell, progress)
        except TrainingInterrupted:
            print(f"{prefix}: interrupted; run the same command again to resume it (finished cells are kept)",
                  file=sys.stderr)
            return None
        except Exception as error:  # noqa: BLE001 - a failed cell is reported and the study goes on
            failed.append(cell)
            reason = f"{type(error).__name__}: {first_line(error)}"
            study.record_failure(cell, reason)
            print(f"{prefix}: FAILED: {reason}", file=sys.stderr, flush=True)
            continue
        print(f"{prefix}: done in {time.perf_counter() - started:.0f} s, {score_line(record)}", flush=True)
    return failed
