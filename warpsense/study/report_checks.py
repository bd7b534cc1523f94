"""The check of a cell's evaluation record before the report reads it (`check_evaluation`): every field the report
reads present, of its type and finite, else a one-line PlanError naming the cell, the file and the field. A damaged
cell is refused, never left out of a mean or a bootstrap."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from warpsense.study.plan import Cell, PlanError
from warpsense.study.study_dir import StudyDir


def cell_name(camera: str, light: str, fold: str, seed: int) -> str:
    """A cell's id and evaluation file (relative to the study directory) from its key, for a message."""
    cell = Cell(camera, light, seed, fold)
    return f"cell {cell.id} ({StudyDir(Path()).run(cell).evaluation})"


def check_evaluation(evaluation: dict, cell: str, path: Path, checked: dict | None = None) -> None:
    """A cell's evaluation holds every field the report reads, present and finite, else a one-line PlanError naming
    the cell, the file and the field: class_names (non-empty distinct names; the same as the cells already
    ``checked``, by (camera, light, fold, seed), whose first the report takes them from), epoch, network_parameters,
    the learned camera's numbers, train_sequences (null or names), and per split: mIoU and each class's IoU (null
    where the class was neither labelled nor predicted) in [0, 1], per-image (TP, FP, FN) pixel counts [N, K, 3]
    (N >= 1 frames, K classes; finite and >= 0) and image_sequences (null or one name per frame). A damaged cell is
    refused, never left out of a mean or a bootstrap."""
    def refuse(field: str, problem: str):
        return PlanError(f"{path}: cell {cell}: {field}: {problem}")

    if not isinstance(evaluation, dict):
        raise refuse("the record", f"expected a JSON object, got {type(evaluation).__name__}")
    splits = evaluation.get("splits")
    if not isinstance(splits, dict) or not splits:
        raise refuse("splits", f"expected an object of the splits judged, got {splits!r}")
    for split, metrics in splits.items():  # the scores first (a missing one is named below, with its field)
        if not isinstance(metrics, dict):
            continue
        scores = metrics.get("per_class_iou")
        values = [*([metrics["miou"]] if "miou" in metrics else []),
                  *(v for v in (scores.values() if isinstance(scores, dict) else ()) if v is not None)]
        if not all(_score(value) for value in values):
            raise PlanError(f"{path}: cell {cell}: {split} scores must be finite and in [0, 1], got mIoU "
                            f"{metrics.get('miou')!r}")
    for field in ("class_names", "epoch", "network_parameters", "camera"):
        if field not in evaluation:
            raise refuse(field, "missing (not an evaluation record, or a damaged one)")
    classes = evaluation["class_names"]
    if not (isinstance(classes, list) and classes and all(isinstance(name, str) and name for name in classes)
            and len(set(classes)) == len(classes)):
        raise refuse("class_names", f"expected a list of distinct class names, got {classes!r}")
    if checked:
        key, first = next(iter(checked.items()))
        if first["class_names"] != classes:
            raise refuse("class_names", f"{', '.join(classes)}; {cell_name(*key)} has {', '.join(first['class_names'])}"
                         ": the cells were judged on other classes (another class table?)")
    for field in ("epoch", "network_parameters"):
        value = evaluation[field]
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise refuse(field, f"expected an integer >= 0, got {value!r}")
    for field in ("train_frames", "labelled_frames"):  # a fold's counts (the report's fold lines), where recorded
        value = evaluation.get(field)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise refuse(field, f"expected null or an integer >= 1, got {value!r}")
    _check_camera(evaluation["camera"], refuse)
    train_sequences = evaluation.get("train_sequences")
    if train_sequences is not None and not _names(train_sequences):
        raise refuse("train_sequences", f"expected null or a list of sequence names, got {train_sequences!r}")
    for split, metrics in splits.items():
        _check_split(metrics, classes, lambda field, problem, split=split: refuse(f"splits.{split}.{field}", problem))


def _names(values) -> bool:
    """Whether ``values`` is a list of strings."""
    return isinstance(values, list) and all(isinstance(value, str) for value in values)


def _score(value) -> bool:
    """Whether ``value`` is a finite score in [0, 1] (not a bool)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and 0 <= value <= 1


def _check_camera(camera, refuse) -> None:
    """The learned camera's numbers the report prints (`warpsense.study.report._learned`) are finite numbers."""
    if not isinstance(camera, dict):
        raise refuse("camera", f"expected an object (the learned camera), got {camera!r}")
    for key in ("exposure_gain", "f_number", "exposure_ms", "analog_gain"):
        value = camera.get(key)
        if key in camera and (isinstance(value, bool) or not isinstance(value, (int, float))
                              or not math.isfinite(value)):
            raise refuse(f"camera.{key}", f"expected a finite number, got {value!r}")
    if "zernike_waves" in camera:
        waves = camera["zernike_waves"]
        on_axis = [row[0] if isinstance(row, list) and row else row for row in waves] if isinstance(waves, list) \
            else [None]
        if not all(isinstance(w, (int, float)) and not isinstance(w, bool) and math.isfinite(w) for w in on_axis):
            raise refuse("camera.zernike_waves", "expected a list of finite numbers (or of rows of them)")


def _check_split(metrics, classes: list[str], refuse) -> None:
    """One split of an evaluation (`check_evaluation`); ``refuse(field, problem)`` makes the error."""
    if not isinstance(metrics, dict):
        raise refuse("", f"expected an object, got {metrics!r}")
    for field in ("miou", "per_class_iou", "image_counts"):
        if field not in metrics:
            raise refuse(field, "missing")
    if not _score(metrics["miou"]):
        raise refuse("miou", f"must be a finite score in [0, 1], got {metrics['miou']!r}")
    per_class = metrics["per_class_iou"]
    if not isinstance(per_class, dict):
        raise refuse("per_class_iou", f"expected an object of class -> IoU, got {per_class!r}")
    for name in classes:
        if name not in per_class:
            raise refuse(f"per_class_iou.{name}", "missing")
        if per_class[name] is not None and not _score(per_class[name]):
            raise refuse(f"per_class_iou.{name}", f"must be null or a finite score in [0, 1], got {per_class[name]!r}")
    try:
        counts = np.asarray(metrics["image_counts"], dtype=np.float64)
    except (ValueError, TypeError):
        counts = None
    if counts is None or counts.ndim != 3 or counts.shape[1:] != (len(classes), 3) or not len(counts):
        shape = "ragged or not numbers" if counts is None else f"shape {list(counts.shape)}"
        raise refuse("image_counts", f"expected per-image (TP, FP, FN) counts [N, {len(classes)}, 3] with N >= 1 "
                     f"frames, got {shape}")
    if not (np.isfinite(counts).all() and (counts >= 0).all()):
        raise refuse("image_counts", "holds negative, NaN or infinite counts")
    sequences = metrics.get("image_sequences")
    if sequences is not None and not (_names(sequences) and len(sequences) == len(counts)):
        raise refuse("image_sequences", f"expected null or one sequence name per frame ({len(counts)}), got "
                     f"{len(sequences) if isinstance(sequences, list) else repr(sequences)}"
                     f"{' entries' if isinstance(sequences, list) else ''}")
