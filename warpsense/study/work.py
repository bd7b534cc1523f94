"""How much training a study's cells hold: the pixels of a step (what the pool's memory per cell is judged by) and
each cell's work (what the local pool and the Slurm executor hand out longest first)."""

from __future__ import annotations

from warpsense.study.plan import Cell, Plan


def step_pixels(plan: Plan) -> int:
    """The most pixels a training step of any of the plan's cells holds (batch x crop height x width)."""
    firsts = {(cell.camera, cell.light): cell for cell in reversed(plan.cells())}  # folds and seeds share a crop
    configs = (plan.config(cell, "runs") for cell in firsts.values())
    return max(c.data.batch_size * c.data.crop_height * c.data.crop_width for c in configs)


def cell_work(plan: Plan, cells: list[Cell]) -> dict[Cell, int]:
    """Each cell's training work, epochs x training frames x crop pixels: what the pool balances over its GPUs and
    hands out longest first (`warpsense.study.pool`). A fold's training frames are the other sequences' (163-406 of
    CamVid's, so its cells run 1.1-2.5x as long as each other). Every cell counts 1 where a training set cannot be
    built (the cells then go in plan order; the cell reports the error when it trains)."""
    from warpsense.data import build_training

    sizes = {}  # training frames by data config: folds and cameras share them
    work = {}
    for cell in cells:
        config = plan.config(cell, "runs")
        key = repr(config.data)
        if key not in sizes:
            try:
                sizes[key] = len(build_training(config.data, config.run.seed))
            except Exception:  # noqa: BLE001 - any cell's own error is its to report when it trains, not the order's
                return dict.fromkeys(cells, 1)
        work[cell] = config.train.epochs * sizes[key] * config.data.crop_height * config.data.crop_width
    return work
