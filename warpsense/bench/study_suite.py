"""The study suite of `warpsense bench`: cells per GPU-hour of a plan's cells run one per GPU and several per GPU,
in one call on one machine, with each cell's score and time compared between the two.

The same cells train twice, into ``OUT/alone`` (one cell per GPU at a time, no MPS) and ``OUT/shared`` (``per_gpu``
at a time on each GPU, under MPS as ``mps`` says). A cell's throughput is 1 / its time alone and ``per_gpu`` / its
time shared; the suite also reports each run's training epochs (median) and the study-level cells per
GPU-hour. A cell's speedup compares steady wall times (`warpsense.study.run_times.steady_run_seconds`: a process's
first epoch, where a fresh worker compiles its kernels, counted at the median of its other epochs): a pool worker
pays that first use with its first cell only, so in a small suite the cells that happen to come first on a worker
would otherwise decide the ratio; the invocations' own cells per GPU-hour (first use included) are reported beside
it. Runs are not bitwise repeatable on CUDA without ``run.deterministic``: the scores are shown side by side
with their difference, which a user compares with the spread of seeds. On a CPU (no GPU given) both invocations run
in this process and a cell repeats exactly.
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path

from warpsense.study.plan import PlanError, load_plan
from warpsense.study.run_times import run_times
from warpsense.study.runner import run_cells
from warpsense.study.study_dir import StudyDir, read_record
from warpsense.train.run_dir import RunDir


class SuiteStopped(Exception):
    """The suite stopped before its comparison: ``code`` 1 (a cell failed) or 130 (interrupted); the message says
    so in one line, and how to go on (a second call resumes: finished cells are kept)."""

    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


def judged_miou(evaluation: dict, source: str | Path = "evaluation") -> tuple[str, float]:
    """(split, mIoU) a cell is judged by: its held-out sequence in a fold, else val; a one-line PlanError naming
    ``source`` (the evaluation's file) and the field where it is missing or not a finite score in [0, 1]."""
    splits = evaluation.get("splits") if isinstance(evaluation, dict) else None
    if not isinstance(splits, dict):
        raise PlanError(f"{source}: splits: expected an object of the splits judged, got {splits!r}")
    split = "heldout" if "heldout" in splits else "val"
    metrics = splits.get(split)
    miou = metrics.get("miou") if isinstance(metrics, dict) else None
    if isinstance(miou, bool) or not isinstance(miou, (int, float)) or not (math.isfinite(miou) and 0 <= miou <= 1):
        raise PlanError(f"{source}: splits.{split}.miou: expected a finite score in [0, 1], got {miou!r}")
    return split, float(miou)


def _cell_times(path: Path) -> dict:
    """{"wall_s": wall seconds of the run, summed over the processes of a resumed one (`run_seconds`),
    "steady_s": the same without a fresh process's first-use costs (`steady_run_seconds`), "epoch_s": the median
    epoch seconds after the first} from its metrics (`RunDir.read_metrics`), read once."""
    records = RunDir(path).read_metrics()
    wall, steady = run_times(records)
    epochs = [record["epoch_time_s"] for record in records[1:] if "epoch_time_s" in record]
    return {"wall_s": wall, "steady_s": steady, "epoch_s": statistics.median(epochs) if epochs else None}


def _invocation(out: Path) -> dict:
    """The last `study run` invocation's throughput entry of a study directory (`StudyDir.read_throughput`)."""
    study = StudyDir(out)
    entries = study.read_throughput()
    if not entries:
        raise PlanError(f"{study.throughput}: no invocation recorded (its cells were not trained by this suite)")
    return entries[-1]


def run_study_suite(plan: str, out: str | Path, cells: int = 0, gpus: list[str] | None = None, per_gpu: int = 2,
                    mps: str = "auto", overrides: tuple[str, ...] = ()) -> dict:
    """Train the first ``cells`` cells of ``plan`` (0 = all) alone and ``per_gpu`` to a GPU; the comparison.

    Args:
        plan: a shipped plan name or a plan TOML path.
        out: the suite's folder (``alone`` and ``shared`` study directories inside; finished cells are kept, so a
            second call resumes).
        gpus: GPU ids of the local pool (None: this process, one cell after another, in both invocations).
        per_gpu: cells at once on each GPU in the shared invocation (>= 2).
        mps: the shared invocation's `warpsense.study.mps` mode ("auto", "on", "off"); the alone one runs without.
        overrides: ``section.key=value`` for every cell (e.g. fewer epochs).

    Returns:
        {"plan", "gpus", "per_gpu", "mps", "cells": [{"cell", "split", "alone": {"miou", "wall_s", "steady_s",
        "epoch_s"}, "shared": {...}, "miou_difference", "speedup"}], "alone"/"shared": the invocations' throughput
        entries, "cells_per_gpu_hour": {"alone", "shared"}, "ratio", "steady_ratio"};
        ``speedup`` is ``per_gpu`` x steady wall alone / steady wall shared (cells per GPU-hour of that cell, first
        use left out), ``steady_ratio`` the same with the cells' steady walls summed, ``ratio`` the invocations'
        cells per GPU-hour as they ran (first use and packing included).
    """
    if per_gpu < 2:
        raise ValueError(f"the study suite compares one cell per GPU with several: --per-gpu must be >= 2, "
                         f"got {per_gpu}")
    loaded = load_plan(plan, tuple(overrides))
    chosen = loaded.cells()[: cells or None]
    out = Path(out)
    alone, shared = out / "alone", out / "shared"
    for name, folder, slots, mode in (("alone", alone, 1, "off"), ("shared", shared, per_gpu, mps)):
        code = run_cells(loaded, folder, chosen, gpus, slots, mps=mode)
        _check_invocation(code, name, folder)
    slots = per_gpu if gpus else 1
    rows = []
    for cell in chosen:
        row = {"cell": cell.id}
        for name, folder in (("alone", alone), ("shared", shared)):
            run = StudyDir(folder).run(cell)
            split, miou = judged_miou(read_record(run.evaluation, dict), run.evaluation)
            row["split"], row[name] = split, {"miou": miou, **_cell_times(run.path)}
        row["miou_difference"] = row["shared"]["miou"] - row["alone"]["miou"]
        row["speedup"] = slots * row["alone"]["steady_s"] / row["shared"]["steady_s"]
        rows.append(row)
    steady = {name: sum(row[name]["steady_s"] for row in rows) for name in ("alone", "shared")}
    invocations = {"alone": _invocation(alone), "shared": _invocation(shared)}
    devices = max(1, len(gpus or []))
    per_hour = {name: entry["cells_per_hour"] / devices for name, entry in invocations.items()}
    return {"suite": "study", "plan": str(plan), "gpus": list(gpus or []), "per_gpu": slots,
            "mps": invocations["shared"].get("mps", False), "overrides": list(overrides), "cells": rows,
            **invocations, "cells_per_gpu_hour": per_hour, "ratio": per_hour["shared"] / per_hour["alone"],
            "steady_ratio": slots * steady["alone"] / steady["shared"]}


def _check_invocation(code: int, name: str, folder: Path) -> None:
    """Stop the suite after an invocation that did not finish its cells, as `warpsense study run` stops: the other
    invocation never starts (its times would be compared with nothing), and a second call resumes both."""
    later = " before the shared invocation" if name == "alone" else ""
    if code == 130:
        raise SuiteStopped(f"study suite: interrupted in the {name} invocation ({folder}){later}; run the same "
                           "command again to resume (finished cells are kept)", 130)
    if code:
        raise SuiteStopped(f"study suite: cells failed in the {name} invocation ({folder}; the reasons above, and "
                           f"`warpsense study status {folder}`); stopped{later}. Run the same command again to retry "
                           "them (finished cells are kept)", 1)


def format_study_suite(record: dict) -> str:
    """The suite's record as a table: a line per cell, then the invocations."""
    lines = [f"study suite: {record['plan']}, {len(record['cells'])} cell(s); alone = one per "
             f"{'GPU' if record['gpus'] else 'process'}, shared = {record['per_gpu']} per GPU"
             f"{' under MPS' if record['mps'] else ''}",
             f"  {'cell':<34} {'mIoU alone':>10} {'shared':>8} {'diff':>8} {'steady alone':>12} {'shared':>8} "
             f"{'per GPU-hour':>12}"]
    for row in record["cells"]:
        lines.append(f"  {row['cell']:<34} {row['alone']['miou']:>10.4f} {row['shared']['miou']:>8.4f} "
                     f"{row['miou_difference']:>+8.4f} {row['alone']['steady_s']:>11.0f}s "
                     f"{row['shared']['steady_s']:>7.0f}s {row['speedup']:>11.2f}x")
    per_hour = record["cells_per_gpu_hour"]
    lines.append(f"  cells per GPU-hour, steady (first use left out): {record['steady_ratio']:.2f}x")
    lines.append(f"  cells per GPU-hour as run: alone {per_hour['alone']:.1f}, shared {per_hour['shared']:.1f}: "
                 f"{record['ratio']:.2f}x")
    return "\n".join(lines)
