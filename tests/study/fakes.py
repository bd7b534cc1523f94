"""A stand-in for training a study's cell: writes the run directory a finished cell leaves (config.json,
metrics.jsonl, evaluation.json) with a score chosen by the test, so that the rounds of adaptive studies (sequential
verdicts, searches) are checked by hand in a second."""

import json
from pathlib import Path

from warpsense.study import slurm, slurm_status
from warpsense.study.study_dir import run_dir

CLASSES = ["sky", "road"]


def evaluation(miou: float, camera: dict | None = None, frames: int = 4) -> dict:
    """An evaluation record of mIoU ``miou`` on ``frames`` frames of one sequence ("val0"): per frame and class
    (TP, FP, FN) = (100 m, 50 (1 - m), 50 (1 - m)), whose IoU is m."""
    counts = [100 * miou, 50 * (1 - miou), 50 * (1 - miou)]
    split = {"miou": miou, "per_class_iou": dict.fromkeys(CLASSES, miou), "image_sequences": ["val0"] * frames,
             "image_counts": [[counts, counts] for _ in range(frames)]}
    return {"epoch": 1, "network_parameters": 10, "camera": camera or {}, "class_names": CLASSES,
            "splits": {"val": split}}


class FakeTraining:
    """``warpsense.study.training.train_cell`` replaced: ``score(config, cell) -> mIoU``; ``trained`` lists the
    cells' ids in the order trained; with ``stop_after`` the next cell raises KeyboardInterrupt (as Ctrl-C would)
    once that many trained."""

    def __init__(self, score, stop_after: int | None = None):
        self.score, self.stop_after, self.trained = score, stop_after, []

    def __call__(self, plan, out, cell, progress=False) -> dict:
        from warpsense.train.engine import TrainingInterrupted

        if self.stop_after is not None and len(self.trained) >= self.stop_after:
            raise TrainingInterrupted(run_dir(out, cell))
        directory = run_dir(Path(out), cell)
        directory.mkdir(parents=True, exist_ok=True)
        config = plan.config(cell, Path(out) / "runs")
        (directory / "config.json").write_text(json.dumps(config.to_dict()))
        (directory / "metrics.jsonl").write_text(json.dumps({"epoch": 0, "setup_s": 1.0, "wall_s": 5.0}) + "\n")
        learned = {"f_number": config.optics.f_number * 0.9, "exposure_ms": config.optics.exposure_ms * 1.2} \
            if config.optics.f_number_learnable else {}
        record = evaluation(self.score(config, cell), learned)
        (directory / "evaluation.json").write_text(json.dumps(record))
        self.trained.append(cell.id)
        return record


def fake_cluster(monkeypatch, arrays: list) -> None:
    """Slurm's commands answered here; a submitted array's tasks run at once in this process (submitit's CellTask),
    and each array's cell ids are appended to ``arrays``."""
    monkeypatch.setattr(slurm, "require_slurm", lambda: None)
    monkeypatch.setattr(slurm, "check_submission", lambda *args: None)
    monkeypatch.setattr(slurm_status, "queue_states", lambda: {})

    def submit(plan, out, cells, options, gpus):
        task = slurm.CellTask(str(Path(plan.source).absolute()), plan.overrides, str(out))
        for cell in cells:
            task(cell)
        arrays.append([cell.id for cell in cells])
        return str(len(arrays))

    monkeypatch.setattr(slurm, "submit", submit)
