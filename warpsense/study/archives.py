"""Finished studies as measurements: the cells of study directories, or of the .tar.xz archives of them that
docs/records keeps (each study directory's plan.json and, per run, evaluation.json and metrics.jsonl), read without
unpacking."""

from __future__ import annotations

import json
import tarfile
from collections.abc import Iterator
from pathlib import Path

RUN_FILES = ("evaluation.json", "metrics.jsonl")


def run_cell(run_name: str) -> tuple[str, str, str, int] | None:
    """(camera, light, fold, seed) of a study's run directory name camera.light[.fold].seedN, None otherwise."""
    parts = run_name.split(".")
    if len(parts) not in (3, 4) or not parts[-1].startswith("seed") or not parts[-1][4:].isdigit():
        return None
    return parts[0], parts[1], parts[2] if len(parts) == 4 else "", int(parts[-1][4:])


def _files(archive: Path) -> Iterator[tuple[str, bytes]]:
    """(path inside, content) of every plan.json and run file of a study archive or folder."""
    wanted = ("plan.json", *RUN_FILES)
    if archive.is_dir():
        for path in sorted(archive.rglob("*")):
            if path.name in wanted and path.is_file():
                yield str(path.relative_to(archive)), path.read_bytes()
        return
    with tarfile.open(archive) as tar:
        for member in tar.getmembers():
            if member.isfile() and Path(member.name).name in wanted:
                yield member.name, tar.extractfile(member).read()


def judged_score(evaluation: dict) -> float:
    """The score a study judges a cell by: the held-out split's mIoU with folds, else the first split's."""
    splits = evaluation["splits"]
    return float((splits.get("heldout") or next(iter(splits.values())))["miou"])


def archive_cells(archives: list[str | Path], metrics: bool = False) -> list[dict]:
    """Every finished cell of the study directories inside ``archives`` (.tar.xz of study directories, or folders):
    {"archive", "directory" (the study directory inside it), "plan" (its plan's name), "camera", "light", "fold",
    "seed", "miou" (`judged_score`)} and, with ``metrics``, "curve": {epoch (0-based): val mIoU} of the epochs its
    metrics.jsonl validated and "epochs" (the last epoch + 1). A cell that another directory of the same plan name
    already holds (a rerun of one plan and its seeds) is counted once, the first in sorted order: reruns of one seed
    are not independent seeds."""
    rows, seen = [], set()
    for archive in archives:
        archive = Path(archive)
        plans, runs = {}, {}
        for name, content in _files(archive):
            parts = Path(name).parts
            if parts[-1] == "plan.json":
                plans[str(Path(*parts[:-1]))] = json.loads(content).get("name", "")
            elif len(parts) >= 3 and parts[-3] == "runs":
                runs.setdefault((str(Path(*parts[:-3])), parts[-2]), {})[parts[-1]] = content
        for (directory, run), files in sorted(runs.items()):
            cell = run_cell(run)
            plan = plans.get(directory, directory)
            if cell is None or "evaluation.json" not in files or (plan, *cell) in seen:
                continue
            seen.add((plan, *cell))
            camera, light, fold, seed = cell
            row = {"archive": archive.name, "directory": directory, "plan": plan, "camera": camera, "light": light,
                   "fold": fold, "seed": seed, "miou": judged_score(json.loads(files["evaluation.json"]))}
            if metrics:
                curve = {}
                for line in files.get("metrics.jsonl", b"").decode().splitlines():
                    record = json.loads(line) if line.strip() else {}
                    if isinstance(record.get("val_miou"), (int, float)) and "epoch" in record:
                        curve[int(record["epoch"])] = float(record["val_miou"])  # a resumed epoch: its last record
                row["curve"] = curve
                row["epochs"] = max(curve) + 1 if curve else 0
            rows.append(row)
    return rows
