"""How early a study's cells rank cameras as their final scores do: what justifies stopping a losing design early.

Two measurements on finished studies (`warpsense.study.archives.archive_cells` with their metrics):

- `epoch_ranks`: within each study, fold and light, the Spearman rank correlation between the cells' validation mIoU
  at an early epoch (metrics.jsonl; the runs validate every few epochs) and their final score, across the cells
  (cameras x seeds) and across the cameras' means over seeds (what ranks designs): would a rung of epochs keep the
  designs that end best?
- `cell_ranks`: within each study and light, the Spearman rank correlation between each camera's first cell (its
  first fold's first seed: the first rung of `warpsense.study.search`'s successive halving) and its mean over all its
  cells, across the cameras: does the first rung keep the designs that end best?

Groups with fewer than ``least`` cameras are left out (a rank correlation of two is +-1 by construction).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

FRACTIONS = (0.1, 0.2, 1 / 3, 0.5, 0.75)
"""Early points of a run, as fractions of its epochs (10%: epoch 15 of 150)."""


def _spearman(a, b) -> float | None:
    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return None
    return float(stats.spearmanr(a, b).statistic)


def _groups(rows: list[dict], keys: tuple[str, ...]) -> dict:
    groups: dict = {}
    for row in rows:
        groups.setdefault(tuple(row[key] for key in keys), []).append(row)
    return groups


def _at(curve: dict, fraction: float, epochs: int) -> tuple[int, float] | None:
    """The first validated epoch at or after ``fraction`` of ``epochs`` (0-based), with its value."""
    wanted = fraction * epochs - 1
    later = [epoch for epoch in curve if epoch >= wanted - 1e-9]
    return (min(later), curve[min(later)]) if later else None


def epoch_ranks(rows: list[dict], fractions=FRACTIONS, least: int = 3) -> list[dict]:
    """Per fraction of the run: {"fraction", "epochs_at" (the epochs used, e.g. [14, 9]: epoch 15 of 150, 10 of
    100), "cells": {"median", "min", "groups"} of the per-group Spearman correlation across cells, "cameras": the same
    across the cameras' means over seeds, "groups" (study directory, fold, light) measured}."""
    out = []
    groups = {key: group for key, group in _groups(rows, ("archive", "directory", "fold", "light")).items()
              if len({row["camera"] for row in group}) >= least}
    for fraction in fractions:
        cells, cameras, used = [], [], set()
        for group in groups.values():
            points = [(row, _at(row["curve"], fraction, row["epochs"])) for row in group if row["curve"]]
            points = [(row, point) for row, point in points if point is not None]
            if len(points) < least:
                continue
            used |= {point[0] for _, point in points}
            rho = _spearman([point[1] for _, point in points], [row["miou"] for row, _ in points])
            if rho is not None:
                cells.append(rho)
            by_camera: dict = {}
            for row, point in points:
                by_camera.setdefault(row["camera"], []).append((point[1], row["miou"]))
            if len(by_camera) >= least:
                early = [np.mean([v for v, _ in values]) for values in by_camera.values()]
                final = [np.mean([f for _, f in values]) for values in by_camera.values()]
                rho = _spearman(early, final)
                if rho is not None:
                    cameras.append(rho)
        out.append({"fraction": fraction, "epochs_at": sorted(used), "cells": _summary(cells),
                    "cameras": _summary(cameras)})
    return out


def cell_ranks(rows: list[dict], least: int = 3, reduction: int = 3, margin: float = 0.0) -> dict:
    """Per study and light with >= ``least`` cameras of >= 2 cells: the Spearman correlation across cameras between
    the first cell (first fold in sorted order, lowest seed) and the camera's mean over its cells; between the first
    fold's mean over seeds and the mean (studies of >= 2 folds); and whether the camera of the best mean would pass a
    first rung that keeps the top 1/``reduction`` of the first cells or those within ``margin`` of their best.
    Returns {"first_cell": summary, "first_fold": summary, "best_kept": studies where it would, "studies":
    [{"study", "light", "cameras", "folds", "first_cell", "first_fold", "best_rank", "best_kept"}]}."""
    studies, first_cells, first_folds = [], [], []
    for (archive, directory, light), group in _groups(rows, ("archive", "directory", "light")).items():
        by_camera: dict = {}
        for row in group:
            by_camera.setdefault(row["camera"], []).append(row)
        by_camera = {camera: cells for camera, cells in by_camera.items() if len(cells) >= 2}
        if len(by_camera) < least:
            continue
        fold = min(row["fold"] for cells in by_camera.values() for row in cells)
        first, first_fold, final = [], [], []
        for cells in by_camera.values():
            ordered = sorted(cells, key=lambda row: (row["fold"], row["seed"]))
            first.append(ordered[0]["miou"])
            in_fold = [row["miou"] for row in cells if row["fold"] == fold]
            first_fold.append(np.mean(in_fold) if in_fold else np.nan)
            final.append(np.mean([row["miou"] for row in cells]))
        folds = len({row["fold"] for cells in by_camera.values() for row in cells})
        rho_cell = _spearman(first, final)
        keep = [i for i, value in enumerate(first_fold) if np.isfinite(value)]
        rho_fold = _spearman([first_fold[i] for i in keep], [final[i] for i in keep]) if folds > 1 else None
        if rho_cell is not None:
            first_cells.append(rho_cell)
        if rho_fold is not None:
            first_folds.append(rho_fold)
        best = int(np.argmax(final))
        rank = 1 + sum(value > first[best] for value in first)
        kept = rank <= max(1, -(-len(first) // reduction)) or max(first) - first[best] <= margin
        studies.append({"study": f"{archive}:{directory}", "light": light, "cameras": len(by_camera), "folds": folds,
                        "first_cell": rho_cell, "first_fold": rho_fold, "best_rank": rank, "best_kept": kept})
    return {"first_cell": _summary(first_cells), "first_fold": _summary(first_folds),
            "best_kept": sum(study["best_kept"] for study in studies), "studies": studies}


def _summary(values: list[float]) -> dict:
    return {"median": float(np.median(values)) if values else None, "min": float(min(values)) if values else None,
            "mean": float(np.mean(values)) if values else None, "groups": len(values)}
