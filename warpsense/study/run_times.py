"""A run's wall time from its metrics log: in total (`run_seconds`) and steady (`steady_run_seconds`: without the
one-off kernel compilation of a process's first epoch), as the study report and the study suite count them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from warpsense.train.run_dir import read_metrics


def _processes(records: list[dict]) -> list[list[dict]]:
    """A run's metrics records by process (a record with ``setup_s`` starts one), only those with ``wall_s``;
    processes without any left out."""
    processes: list[list[dict]] = [[]]
    for record in records:
        if "setup_s" in record and processes[-1]:
            processes.append([])
        if "wall_s" in record:
            processes[-1].append(record)
    return [records for records in processes if records]


def _total_seconds(processes: list[list[dict]]) -> float | None:
    return sum(float(records[-1]["wall_s"]) for records in processes) if processes else None


def _steady_seconds(processes: list[list[dict]]) -> float | None:
    if not processes:
        return None
    total = 0.0
    for records in processes:
        walls = [float(r["wall_s"]) for r in records]
        total += walls[-1]
        if len(walls) > 1:
            first = walls[0] - float(records[0].get("setup_s", 0.0))
            total += float(np.median(np.diff(walls))) - first
    return total


def run_times(records: list[dict]) -> tuple[float | None, float | None]:
    """(`run_seconds`, `steady_run_seconds`) of a run's metrics ``records`` (`read_metrics`), for a caller that
    holds them already: the log read once for both times."""
    processes = _processes(records)
    return _total_seconds(processes), _steady_seconds(processes)


def run_seconds(metrics_path: Path) -> float | None:
    """A run's wall seconds from its metrics log (`RunDir.METRICS`): each process's ``wall_s`` at its last epoch (setup,
    training and evaluation), summed over the processes of a resumed run (a record with ``setup_s`` starts one); None
    without records. The work an interrupted process did after its last epoch is not counted."""
    return _total_seconds(_processes(read_metrics(metrics_path)))


def steady_run_seconds(metrics_path: Path) -> float | None:
    """`run_seconds` without the one-off costs of a fresh process: in each process (a record with ``setup_s`` starts
    one) the first epoch's share of ``wall_s`` (``wall_s`` minus ``setup_s``: training and evaluation, where the Warp
    kernels of a cold cache compile) is counted at the median of that process's other epochs'
    shares (their ``wall_s`` differences). Setup (data loading) is kept. A process with one epoch has nothing to
    compare with and is counted as it ran, so a run of one epoch per process is its `run_seconds`. None without
    records."""
    return _steady_seconds(_processes(read_metrics(metrics_path)))
