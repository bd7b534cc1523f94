"""Training one cell of a study in this process (`train_cell`: what the in-process runner, a pool worker and a
Slurm task each call, through this module so that a test can stand in for it), its score in words, and the check
that this machine can train a plan's cells at all."""

from __future__ import annotations

from pathlib import Path

from warpsense.study.plan import Cell, Plan, PlanError
from warpsense.study.study_dir import StudyDir


def train_cell(plan: Plan, out: Path, cell: Cell, progress: bool = False) -> dict:
    """Train (or resume) and evaluate one cell in this process; returns its evaluation record."""
    from warpsense.train.engine import train
    from warpsense.train.run_dir import set_aside

    study = StudyDir(out)
    run = study.run(cell)
    state = study.cell_state(cell)
    if state != "done":
        config = plan.config(cell, study.runs)
        if state == "new" and run.holds_run():  # stopped before its first resume point: its best checkpoint kept
            kept = set_aside(run.path)
            print(f"{cell.id}: an attempt stopped before its first resume point left a best checkpoint: kept in "
                  f"{kept}; the cell trains from the start", flush=True)
        train(config, resume=run.path if state == "partial" else False, progress=progress)
    return study.read_evaluation(cell)


def score_line(record: dict) -> str:
    """A cell's evaluation in words: "val mIoU 0.7123, test mIoU ..." (its splits in order)."""
    return ", ".join(f"{split} mIoU {metrics['miou']:.4f}" for split, metrics in record["splits"].items())


def check_runnable(plan: Plan, cells: list[Cell], local: bool = True) -> None:
    """Refuse, before anything is written, cells this machine cannot train (``local``: they run here): a config that
    asks for a device it does not have (run.device = "cuda" without CUDA) or a CUDA-only feature on the CPU
    (train.cuda_graph), in one line naming the key and the cells (each distinct camera and light checked once).
    A study whose cells all failed at once would have written its plan and refused the corrected command."""
    from warpsense.system import resolve_device

    if not local:
        return
    checked = set()
    for cell in cells:
        if (cell.camera, cell.light) in checked:
            continue
        checked.add((cell.camera, cell.light))
        config = plan.config(cell, "runs")
        try:
            device = resolve_device(config.run.device)
        except ValueError as error:
            raise PlanError(f"{plan.source}: cell {cell.id}: run.device = {config.run.device!r}: {error}") from None
        if config.train.cuda_graph and device.type != "cuda":
            raise PlanError(f"{plan.source}: cell {cell.id}: train.cuda_graph needs a CUDA device and this machine "
                            f"trains on {device.type} (--set train.cuda_graph=false)")
