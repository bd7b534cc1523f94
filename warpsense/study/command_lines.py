"""The command lines of a study's cells: `warpsense study run` of a plan into a study directory with the plan's
command-line overrides, for one cell (what `--plan-only` prints for a scheduler of the user's) or for a worker of the
local pool (`warpsense.study.worker`)."""

from __future__ import annotations

import shlex
from pathlib import Path

from warpsense.study.plan import Cell, Plan


def study_command(plan: Plan, out: Path, *options: str) -> list[str]:
    """`warpsense study run` of ``plan`` into ``out`` with ``options`` and the plan's command-line overrides."""
    command = ["warpsense", "study", "run", plan.source, "--out", str(out), *options]
    for text in plan.overrides:
        command += ["--set", text]
    return command


def cell_command(plan: Plan, out: Path, cell: Cell, reuse: list[Path] | tuple = ()) -> list[str]:
    """The command that runs one cell (what `--plan-only` prints, for a scheduler), copying it in from ``reuse``
    (study directories) where one holds the same training, as the local run would."""
    return study_command(plan, out, "--cell", cell.id,
                         *(option for path in reuse for option in ("--reuse", str(path))))


def plan_commands(plan: Plan, out: Path, reuse: list[Path] | tuple = (), cells: list[Cell] | None = None) -> list[str]:
    """One shell command per cell (default: every cell of the plan), for a scheduler of the user's (with
    ``reuse``'s --reuse options)."""
    return [shlex.join(cell_command(plan, out, cell, reuse)) for cell in (plan.cells() if cells is None else cells)]
