"""Damaged records of a study directory (issue 76): every read of a cell's evaluation, a run's config and metrics,
the throughput and Slurm records names the file and the field in one line; a cell whose evaluation lacks a field
the report uses, or holds one that is not finite, is refused by name, never left out of a mean or a bootstrap.
The studies here are fabricated (no training): each cell's evaluation.json, config.json and metrics.jsonl."""

import json
from pathlib import Path

import pytest

from tests.reliability.conftest import assert_clean_failure
from warpsense.study import load_plan
from warpsense.study.plan import PlanError
from warpsense.study.report import study_record
from warpsense.study.study_dir import StudyDir, evaluation_path, record_plan, run_dir
from warpsense.train.run_dir import read_metrics

CLASSES = ["sky", "road"]
FRAMES = 4


def _evaluation(miou: float, frames: int = FRAMES) -> dict:
    """A finished cell's evaluation.json as the engine writes it: every field the report reads."""
    counts = [[[10, 5, 5], [20, 2, 3]] for _ in range(frames)]
    split = {"miou": miou, "pixel_accuracy": 0.8, "per_class_iou": {"sky": miou, "road": miou},
             "image_counts": counts, "image_sequences": ["val0"] * frames}
    return {"epoch": 1, "class_names": list(CLASSES), "num_classes": 2, "network_parameters": 100,
            "camera": {"exposure_gain": 1.0}, "holdout_sequence": "", "train_sequences": ["train0"],
            "splits": {"val": split}}


def _study(tmp_path: Path) -> tuple[Path, object]:
    """The smoke plan's cells, finished without training (a score per camera and seed)."""
    plan = load_plan("smoke")
    out = tmp_path / "study"
    record_plan(plan, out)
    for index, cell in enumerate(plan.cells()):
        folder = run_dir(out, cell)
        folder.mkdir(parents=True)
        evaluation_path(out, cell).write_text(json.dumps(_evaluation(0.3 + 0.01 * index)))
        (folder / "config.json").write_text(json.dumps(plan.config(cell, out / "runs").to_dict()))
        (folder / "metrics.jsonl").write_text(json.dumps({"epoch": 0, "setup_s": 1.0, "wall_s": 5.0}) + "\n")
    return out, plan


def _damage(out: Path, cell, change) -> Path:
    path = evaluation_path(out, cell)
    evaluation = json.loads(path.read_text())
    change(evaluation)
    path.write_text(json.dumps(evaluation))
    return path


def _refused(out: Path, *parts: str) -> str:
    with pytest.raises(PlanError) as error:
        study_record(out, resamples=20)
    message = str(error.value)
    assert len(message.splitlines()) == 1, message
    for part in parts:
        assert part in message, message
    return message


def test_the_fabricated_study_reports(tmp_path):
    out, plan = _study(tmp_path)
    record = study_record(out, resamples=20)
    assert len(record["cells"]) == len(plan.cells()) and not record["missing"]
    assert all(comparison["bootstrap"] is not None for comparison in record["splits"]["val"]["comparisons"])


def _delete(*keys):
    def change(evaluation):
        target = evaluation
        for key in keys[:-1]:
            target = target[key]
        del target[keys[-1]]
    return change


def _set(value, *keys):
    def change(evaluation):
        target = evaluation
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value
    return change


DAMAGES = {
    "no image counts": (_delete("splits", "val", "image_counts"), "splits.val.image_counts: missing"),
    "no per-class IoU": (_delete("splits", "val", "per_class_iou"), "splits.val.per_class_iou: missing"),
    "a class's IoU missing": (_delete("splits", "val", "per_class_iou", "road"), "splits.val.per_class_iou.road: "
                                                                                 "missing"),
    "no mIoU": (_delete("splits", "val", "miou"), "splits.val.miou: missing"),
    "no class names": (_delete("class_names"), "class_names: missing"),
    "no epoch": (_delete("epoch"), "epoch: missing"),
    "no learned camera": (_delete("camera"), "camera: missing"),
    "no splits": (_delete("splits"), "splits: expected an object"),
    "counts of another class count": (_set([[[1, 2, 3]]] * FRAMES, "splits", "val", "image_counts"),
                                      "splits.val.image_counts: expected per-image (TP, FP, FN) counts [N, 2, 3]"),
    "ragged counts": (_set([[[1, 2, 3], [1, 2]]] * FRAMES, "splits", "val", "image_counts"),
                      "splits.val.image_counts: expected per-image"),
    "no frames": (_set([], "splits", "val", "image_counts"), "splits.val.image_counts: expected per-image"),
    "NaN counts": (_set([[[float("nan"), 1, 1], [1, 1, 1]]] * FRAMES, "splits", "val", "image_counts"),
                   "splits.val.image_counts: holds negative, NaN or infinite counts"),
    "negative counts": (_set([[[-1, 1, 1], [1, 1, 1]]] * FRAMES, "splits", "val", "image_counts"),
                        "splits.val.image_counts: holds negative"),
    "sequences of another length": (_set(["val0"] * (FRAMES - 1), "splits", "val", "image_sequences"),
                                    "splits.val.image_sequences: expected null or one sequence name per frame (4)"),
    "infinite exposure gain": (_set(float("inf"), "camera", "exposure_gain"), "camera.exposure_gain: expected a "
                                                                              "finite number"),
}
DAMAGES["other class names"] = (lambda evaluation: (_set(["sky", "car"], "class_names")(evaluation), _set(
    {"sky": 0.3, "car": 0.3}, "splits", "val", "per_class_iou")(evaluation)), "class_names: sky, car; cell "
    "rggb/night/0 (runs/rggb.night.seed0/evaluation.json) has sky, road")


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_a_damaged_evaluation_is_refused_naming_the_cell_file_and_field(tmp_path, damage):
    out, plan = _study(tmp_path)
    change, field = DAMAGES[damage]
    cell = plan.cells()[1]  # not the first: that one's class names are the report's
    path = _damage(out, cell, change)
    _refused(out, str(path), f"cell {cell.id}", field)


def test_a_damaged_cell_is_refused_by_the_command_in_one_line(tmp_path, capsys):
    """`study report` on a cell without its per-image counts said `error: image_counts`."""
    out, plan = _study(tmp_path)
    path = _damage(out, plan.cells()[2], _delete("splits", "val", "image_counts"))
    assert_clean_failure(capsys, ["study", "report", str(out), "--resamples", "20"],
                         (str(path), "cell learned/night/0", "splits.val.image_counts: missing"))


def test_a_pair_judged_on_other_frames_is_refused_not_dropped_from_the_bootstrap(tmp_path):
    """A camera's cell judged on 3 frames, its reference on 4 (each record whole by itself): the pair was left out of
    the bootstrap without a word (the comparison printed '-' for its bootstrap interval)."""
    out, plan = _study(tmp_path)
    cell = next(cell for cell in plan.cells() if cell.camera == "rccb" and cell.seed == 1)
    evaluation_path(out, cell).write_text(json.dumps(_evaluation(0.4, frames=FRAMES - 1)))
    _refused(out, "cell rccb/night/1 (runs/rccb.night.seed1/evaluation.json)", "judged on other frames than the "
             "reference cell rggb/night/1 (runs/rggb.night.seed1/evaluation.json)")
    # the same frame count from other sequences is other frames too
    other = _evaluation(0.4)
    other["splits"]["val"]["image_sequences"] = ["val1"] * FRAMES
    evaluation_path(out, cell).write_text(json.dumps(other))
    _refused(out, "cell rccb/night/1", "judged on other frames than the reference cell rggb/night/1")


def test_a_torn_evaluation_and_throughput_entry_are_named(tmp_path, capsys):
    out, plan = _study(tmp_path)
    (out / "throughput.json").write_text(json.dumps([{"cells_finished": 2, "seconds": 3.0}]))
    assert_clean_failure(capsys, ["study", "report", str(out), "--resamples", "20"],
                         (str(out / "throughput.json"), "entry 1: cells_per_hour: expected a finite number"))
    with pytest.raises(PlanError, match="entry 1: expected a JSON object"):
        (out / "throughput.json").write_text("[3]")
        StudyDir(out).read_throughput()
    (out / "throughput.json").unlink()
    path = evaluation_path(out, plan.cells()[0])
    path.write_text('{"epoch": 1, "splits": {"val"')
    assert_clean_failure(capsys, ["study", "report", str(out), "--resamples", "20"], (str(path), "unreadable"))


def test_the_learned_path_of_a_map_needs_its_config_and_metrics(tmp_path):
    """A learned camera's config.json torn, or an epoch's record without the learned value: the camera was left off
    the design map without a word."""
    from tests.study.test_maps import _fabricate, _plan
    from warpsense.study.maps import LEARNED_KEYS

    plan = load_plan(_plan(tmp_path), ["study.folds=sequence"])
    keys = [(fold, seed) for fold in ("train0", "val0") for seed in (0, 1)]
    cameras = ["map_f1p4_t3", "map_f1p4_t30", "map_f4_t3", "map_f4_t30", "learned"]
    scores = {camera: {key: 0.3 + 0.01 * n for key in keys} for n, camera in enumerate(cameras)}
    study = tmp_path / "study"
    _fabricate(study, plan, scores, {key: [4.0, 3.0, 2.5] for key in keys})
    assert study_record(study, resamples=20)["maps"][0]["learned"][0]["camera"] == "learned"
    learned = next(cell for cell in plan.cells() if cell.camera == "learned")
    config = run_dir(study, learned) / "config.json"
    saved = config.read_text()
    config.write_text(saved[:40])
    _refused(study, str(config), "unreadable")
    config.write_text(saved)
    metrics = run_dir(study, learned) / "metrics.jsonl"
    records = [json.loads(line) for line in metrics.read_text().splitlines()]
    del records[1][LEARNED_KEYS["optics.f_number"][1]]
    metrics.write_text("".join(json.dumps(record) + "\n" for record in records))
    _refused(study, str(metrics), "epoch 1: f_number: expected the learned value")


@pytest.mark.parametrize("line, field", [
    ("[1, 2]", "expected a JSON object"),
    ('{"epoch": "3"}', "epoch: expected an integer >= 0"),
    ('{"epoch": 1, "wall_s": "ten"}', "wall_s: expected a finite number of seconds"),
    ('{"epoch": 1, "setup_s": -1.0}', "setup_s: expected a finite number of seconds"),
])
def test_a_damaged_metrics_record_is_named_with_its_line_and_field(tmp_path, line, field):
    """A record that is not an epoch's (a list) was dropped without a word; a time that is text failed inside the
    report's sum with float()'s message alone."""
    path = tmp_path / "metrics.jsonl"
    path.write_text(f'{{"epoch": 0, "wall_s": 1.0}}\n{line}\n{{"epoch": 2, "wall_s": 3.0}}\n')
    with pytest.raises(ValueError) as error:
        read_metrics(path)
    assert str(error.value) == f"{path}:2: {field}" or str(error.value).startswith(f"{path}:2: {field}")
    path.write_bytes(b'{"epoch": 0}\n\xff\xfe\n')
    with pytest.raises(ValueError, match=f"{path}: unreadable"):
        read_metrics(path)


def test_a_reused_studys_torn_config_is_named_before_anything_is_written(tmp_path, capsys):
    """`study run --reuse DIR` over a run whose config.json is torn printed json's message alone."""
    source, plan = _study(tmp_path)
    config = run_dir(source, plan.cells()[0]) / "config.json"
    config.write_text('{"run": {"name": ')
    out = tmp_path / "new"
    assert_clean_failure(capsys, ["study", "run", "smoke", "--out", str(out), "--reuse", str(source), "--gpus",
                                  "none"], (str(config), "unreadable"), watched=tmp_path / "none")
    assert not out.exists()
    config.write_text("[]")
    assert_clean_failure(capsys, ["study", "run", "smoke", "--out", str(out), "--reuse", str(source), "--gpus",
                                  "none"], (str(config), "expected a JSON object"))
    assert not out.exists()
    config.unlink()
    # a torn evaluation of a run to reuse: named before it is copied in as a finished cell
    cell = plan.cells()[1]
    evaluation_path(source, cell).write_text('{"splits": ')
    assert_clean_failure(capsys, ["study", "run", "smoke", "--out", str(out), "--reuse", str(source), "--gpus",
                                  "none"], (str(evaluation_path(source, cell)), "unreadable"))
    assert not out.exists()


@pytest.mark.parametrize("text, field", [("{}", "submissions: expected a list"),
                                         ('{"submissions": [{"job_id": "7"}]}', "submission 1: cells: expected"),
                                         ('{"submissions": [{"cells": {"rggb/night/0": "7_0"}}]}',
                                          "submission 1: job_id: expected")])
def test_a_damaged_slurm_record_is_named_with_its_field(tmp_path, capsys, text, field):
    out, _ = _study(tmp_path)
    (out / "slurm").mkdir()
    (out / "slurm" / "jobs.json").write_text(text)
    assert_clean_failure(capsys, ["study", "status", str(out)], (str(out / "slurm" / "jobs.json"), field))


def test_status_names_a_cells_damaged_config_and_shows_the_others(tmp_path, capsys):
    """`study status` read a cell's config.json for its epoch count and said 'of ?' without a word on why."""
    from warpsense.cli import main

    out, plan = _study(tmp_path)
    first = plan.cells()[0]
    evaluation_path(out, first).unlink()  # not finished: its status reads the metrics and the config
    (run_dir(out, first) / "config.json").write_text('{"train": ')
    assert main(["study", "status", str(out)]) == 0
    line = next(line for line in capsys.readouterr().out.splitlines() if line.split()[:1] == [first.id])
    assert "epoch 1 of ?" in line and str(run_dir(out, first) / "config.json") in line and "unreadable" in line
