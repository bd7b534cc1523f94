"""Sequence folds: frames know their sequence, a fold trains on the other sequences of train + val and is judged on
its own, and `warpsense study` runs, resumes and reports folds (per-sequence rows); bad fold plans are one-line
errors with nothing written."""

import json
from pathlib import Path

import pytest

from warpsense.cli import main
from warpsense.config import ConfigError, load_config
from warpsense.data import DatasetError, build_fold, frame_sequences, sequence_fold, sequence_names
from warpsense.data.datasets import KITTI360, CamVid, Cityscapes
from warpsense.data.scenes import StreetScenes
from warpsense.resources import CONFIG_DIR
from warpsense.study import load_plan, render_text, run_cells, study_record
from warpsense.study.plan import PlanError
from warpsense.train import engine

FAST = ["train.epochs=2", "data.scenes_train=8", "data.scenes_val=8", "train.eval_every=2", "study.folds=sequence",
        "study.seeds=[0]", "data.scene_height=32", "data.scene_width=48", "data.crop_height=32", "data.crop_width=48"]


def _plan_file(tmp_path: Path, extra: str = "", study: str = "") -> Path:
    text = (CONFIG_DIR / "studies" / "smoke.toml").read_text()
    path = tmp_path / "plan.toml"
    path.write_text(text.replace('reference = "rggb"\n', f'reference = "rggb"\n{study}') + extra)
    return path


def test_sequences_of_each_dataset():
    assert CamVid.sequence_of(Path("train/0016E5_07959.png")) == "0016E5"
    assert Cityscapes.sequence_of(Path("leftImg8bit/train/aachen/aachen_000000_000019_leftImg8bit.png")) == "aachen"
    drive = "2013_05_28_drive_0003_sync"
    assert KITTI360.sequence_of(Path(f"data_2d_raw/{drive}/image_00/data_rect/0000000001.png")) == drive
    with pytest.raises(DatasetError, match="frame.png: no sequence prefix"):
        CamVid.sequence_of(Path("train/frame.png"))
    with pytest.raises(DatasetError, match="no drive folder"):
        KITTI360.sequence_of(Path("images/1.png"))
    scenes = StreetScenes(count=6, height=8, width=8, sequence_blocks=3, stream="val")
    assert scenes.sequences == ["val0", "val0", "val1", "val1", "val2", "val2"]


def test_sequence_fold_cardinality_and_errors():
    train = StreetScenes(count=4, height=8, width=8, sequence_blocks=2)
    val = StreetScenes(count=2, height=8, width=8, seed=5, sequence_blocks=1, stream="val")
    rest, held = sequence_fold([train, val], "train1")
    assert held.frames == [(0, 2), (0, 3)] and rest.frames == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert held.sequences == ["train1", "train1"] and set(rest.sequences) == {"train0", "val0"}
    assert (held[1][0] == train[3][0]).all() and (rest[2][1] == val[0][1]).all()  # the frames themselves
    with pytest.raises(DatasetError, match="'train7' holds no frame; sequences: train0, train1, val0"):
        sequence_fold([train, val], "train7")
    with pytest.raises(DatasetError, match="holds every frame"):
        sequence_fold([StreetScenes(count=2, height=8, width=8)], "train0")
    with pytest.raises(DatasetError, match="carry no sequence names"):
        frame_sequences(object())


def test_camvid_folds_by_drive(shared_data):
    config = load_config("camvid", [f'data.root="{shared_data / "camvid"}"'])
    assert sequence_names(config.data) == ["0001TP", "0006R0", "0016E5"]
    # train holds 0001TP 62, 0006R0 101, 0016E5 204; val 101 more of 0016E5
    for drive, held_count in (("0001TP", 62), ("0006R0", 101), ("0016E5", 305)):
        fold = load_config("camvid", [f'data.root="{shared_data / "camvid"}"', f'data.holdout_sequence="{drive}"'])
        held, train = build_fold(fold.data, train=False), build_fold(fold.data, train=True)
        assert len(held) == held_count and len(train) == 468 - held_count
        assert set(held.sequences) == {drive} and drive not in set(train.dataset.sequences)


def test_camvid_train_plus_val_joins_the_lists(shared_data):
    joined = CamVid(shared_data / "camvid", "train+val")
    assert len(joined) == 367 + 101 and joined.pairs[-1] == CamVid(shared_data / "camvid", "val").pairs[-1]
    with pytest.raises(DatasetError, match="test.txt: CamVid split list not found"):
        CamVid(shared_data / "camvid", "train+test")


def test_holdout_sequence_config_checks():
    with pytest.raises(ConfigError, match="data.holdout_sequence and data.holdout_prefix both"):
        load_config(None, ['data.holdout_sequence="train0"', 'data.holdout_prefix="x"'])
    with pytest.raises(ConfigError, match="data.holdout_sequence must be a sequence name"):
        load_config(None, ['data.holdout_sequence="a/b"'])


def test_camvid_cameras_plan_lists_a_cell_per_drive_and_seed_with_sequence_folds(shared_data, tmp_path, capsys):
    """The drive folds stay for a user with many drives: the shipped plan by sequence folds prints each fold's regime
    (the third trains on 35% of the frames: why CamVid's default is block folds) and a cell per drive and seed."""
    root = f'data.root="{shared_data / "camvid"}"'
    assert main(["study", "run", "camvid_cameras", "--out", "unused", "--plan-only", "--set", "study.folds=sequence",
                 "--set", root]) == 2
    assert 'study.blocks: block folds\' blocks needs folds = "blocks"' in capsys.readouterr().err
    text = (CONFIG_DIR / "studies" / "camvid_cameras.toml").read_text()
    plan = tmp_path / "plan.toml"
    plan.write_text(text.replace("\nblocks = 5 ", "\n# ").replace("\nblock_buffer = 30 ", "\n# "))
    assert main(["study", "run", str(plan), "--out", str(tmp_path / "s"), "--plan-only", "--set",
                 "study.folds=sequence", "--set", root]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[:3] == ["# fold 0001TP: train 406 frames (87% of the labelled frames), judge 62 frames",
                         "# fold 0006R0: train 367 frames (78% of the labelled frames), judge 101 frames",
                         "# fold 0016E5: train 163 frames (35% of the labelled frames), judge 305 frames"]
    cells = [line.split("--cell ")[1].split()[0] for line in lines[3:]]
    night = {cell for cell in cells if cell.startswith("fixed_isp/night/")}
    assert night == {f"fixed_isp/night/{drive}/{seed}" for drive in ("0001TP", "0006R0", "0016E5") for seed in range(3)}
    assert len(cells) == (10 + 4) * 3 * 3  # 10 cameras at night (the control and the twin among them), 4 by day
    assert not Path("unused").exists() and not (tmp_path / "s").exists()


@pytest.mark.parametrize(("study", "overrides", "message"), [
    ('folds = "sequence"\nsequences = ["train0", "nowhere"]\n', [],
     "study.sequences: 'nowhere' holds no frame of the labelled splits (train, val); sequences: train0, val0"),
    ('folds = "loo"\n', [], "study.folds: 'loo' is not a protocol; valid: none, blocks, sequence"),
    ('sequences = ["train0"]\n', [], "study.sequences: held-out sequences need folds = \"sequence\""),
    ('folds = "sequence"\n', ["data.holdout_prefix=train"], "data.holdout_sequence and data.holdout_prefix both"),
    ("", ["study.folds=sequence", "data.dataset=camvid", "data.root=ROOT"], 'study.folds = "sequence" lists'),
    ("", ["study.folds=sequence", "train.epoch=3"], "train.epoch: unknown key"),  # the key named, not study.folds
])
def test_bad_fold_plans_are_one_line_errors_with_nothing_written(tmp_path, study, overrides, message, capsys):
    plan = _plan_file(tmp_path, study=study)
    root = tmp_path / "camvid"  # a CamVid copy whose frames are not named SEQUENCE_FRAME
    (root / "img").mkdir(parents=True)
    (root / "train.txt").write_text("img/a.png img/a.png\n")
    (root / "val.txt").write_text("img/b.png img/b.png\n")
    overrides = [text.replace("ROOT", str(root)) for text in overrides]
    out = tmp_path / "study"
    arguments = ["study", "run", str(plan), "--out", str(out)]
    for text in overrides:
        arguments += ["--set", text]
    assert main(arguments) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and str(plan) in error and message in error
    if "data.dataset=camvid" in overrides:
        assert "a.png: no sequence prefix in the file name" in error
    if "train.epoch=3" in overrides:
        assert "study.folds" not in error
    assert not out.exists()


def test_smoke_study_by_sequence_folds_runs_resumes_and_reports(tmp_path, monkeypatch, capsys):
    plan = load_plan(_plan_file(tmp_path), FAST)
    assert plan.sequences == ("train0", "val0")
    ids = [cell.id for cell in plan.cells()]
    assert ids[:4] == ["rggb/night/train0/0", "rccb/night/train0/0", "learned/night/train0/0", "rggb/night/val0/0"]
    assert len(ids) == 3 * 2
    out = tmp_path / "study"
    write_epoch = engine._write_epoch

    def interrupting(run_dir, *args, **kwargs):  # Ctrl-C after the first epoch of the fourth cell
        write_epoch(run_dir, *args, **kwargs)
        if run_dir.name == "rggb.night.val0.seed0":
            raise KeyboardInterrupt

    monkeypatch.setattr(engine, "_write_epoch", interrupting)
    assert run_cells(plan, out) == 130
    monkeypatch.setattr(engine, "_write_epoch", write_epoch)
    trained = []
    real_train = engine.train
    monkeypatch.setattr(engine, "train", lambda config, resume=False, **kw: trained.append(
        (config.run.name, config.data.holdout_sequence, bool(resume))) or real_train(config, resume=resume, **kw))
    assert run_cells(plan, out) == 0
    assert trained[0] == ("rggb.night.val0.seed0", "val0", True)  # the interrupted fold resumed ...
    assert all(name != "rggb.night.train0.seed0" for name, _, _ in trained)  # ... the finished ones were kept
    assert [name for name, _, _ in trained] == ["rggb.night.val0.seed0", "rccb.night.val0.seed0",
                                                "learned.night.val0.seed0"]
    capsys.readouterr()

    evaluation = json.loads((out / "runs" / "rccb.night.train0.seed0" / "evaluation.json").read_text())
    assert evaluation["holdout_sequence"] == "train0" and evaluation["train_sequences"] == ["val0"]
    assert list(evaluation["splits"]) == ["heldout"]
    assert evaluation["splits"]["heldout"]["image_sequences"] == ["train0"] * 8  # judged on the 8 train scenes

    record = study_record(out, resamples=50, block=3)
    part = record["splits"]["heldout"]
    assert record["folds"] == "sequence" and part["shared_sequences"] == []
    group = part["groups"][0]
    assert group["folds"] == ["train0", "val0"] and group["cells"] == 2 and group["miou"]["folds"] == 2
    assert [(row["sequence"], sorted(row["cameras"])) for row in part["per_sequence"]] == [
        ("train0", ["learned", "rccb", "rggb"]), ("val0", ["learned", "rccb", "rggb"])]
    comparison = part["comparisons"][0]
    assert comparison["paired"]["seeds"] == [("train0", 0), ("val0", 0)] and comparison["bootstrap"]["block"] == 3
    text = render_text(record)
    assert "per fold (held-out block or sequence)" in text and "night/train0" in text and "night/val0" in text
    assert "paired over (fold, seed)" in text
    with pytest.raises(SystemExit) as exited:
        main(["study", "report", str(out), "--resamples", "0"])
    assert exited.value.code == 2 and "argument --resamples: must be >= 1" in capsys.readouterr().err


@pytest.mark.parametrize("miou", [float("nan"), float("inf"), 1.5, -0.1, "0.5"])
def test_report_refuses_a_cell_with_scores_that_are_not_finite_in_0_1(tmp_path, miou):
    from warpsense.study.study_dir import evaluation_path, record_plan

    plan = load_plan("smoke")
    out = tmp_path / "study"
    record_plan(plan, out)
    cell = plan.cells()[0]
    path = evaluation_path(out, cell)
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"epoch": 1, "splits": {"val": {"miou": miou, "per_class_iou": {"sky": 0.5}}}}))
    with pytest.raises(PlanError) as error:
        study_record(out, resamples=10)
    message = str(error.value)
    assert len(message.splitlines()) == 1 and str(path) in message and f"cell {cell.id}" in message
    assert "val scores must be finite and in [0, 1]" in message


def test_eval_scores_a_fold_checkpoint_on_its_held_out_sequence(tmp_path, capsys):
    from warpsense.commands.eval import run_eval
    from warpsense.train.engine import train

    config = load_config(None, ["data.holdout_sequence=\"train0\"", "data.scenes_train=8", "data.scenes_val=8",
                                "data.scene_height=32", "data.scene_width=48", "data.crop_height=32",
                                "data.crop_width=48", "model.width=8", "train.epochs=1", "train.warmup_epochs=0",
                                "train.plots=false", "run.device=\"cpu\"", f"run.output_dir=\"{tmp_path}\""])
    run = train(config, progress=False)
    evaluation = json.loads((run / "evaluation.json").read_text())["splits"]["heldout"]
    checkpoint = str(run / "checkpoint_last.safetensors")
    payload = run_eval(checkpoint, None, None, "heldout", device="cpu", progress=False)
    assert payload["num_images"] == 8 and payload["miou"] == pytest.approx(evaluation["miou"])
    run_eval(checkpoint, None, None, "val", device="cpu", progress=False)
    assert "note: the checkpoint trained on the frames of val from val0 (its fold held out train0 only)" in \
        capsys.readouterr().out


def test_report_help_and_heatmap_speak_in_the_units_they_print(tmp_path, monkeypatch, capsys):
    """`study report --help` says "95%" (not "95%%"); the per-class heatmap's colour bar is in the IoU points its cells
    print, and a cell on the colour map's dark end is labelled in white."""
    import matplotlib.figure

    from warpsense.study.report import plot_study

    with pytest.raises(SystemExit):
        main(["study", "report", "--help"])
    help_text = capsys.readouterr().out
    assert "95%" in help_text and "%%" not in help_text
    record = {"study": "s", "reference": "a", "level": 0.95, "plan": {"cameras": [{}, {}]}, "cells": [],
              "splits": {"val": {
                  "groups": [{"camera": c, "light": "night", "miou": {"mean": 0.5, "low": 0.4, "high": 0.6},
                              "per_class_iou": {"sky": None, "road": None}} for c in ("a", "b")],
                  "comparisons": [{"camera": "b", "light": "night", "verdict": "worse",
                                   "per_class_delta": {"sky": -0.05, "road": 0.001}}]}}}
    figures = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda self, *a, **k: figures.append(self))
    plot_study(record, tmp_path / "p.png")
    texts = {text.get_text(): text.get_color() for axis in figures[0].axes for text in axis.texts}
    assert texts == {"-5.0": "white", "+0.1": "black"}
    colour_bar = figures[0].axes[-1]
    assert "points x100" in colour_bar.get_ylabel() and colour_bar.get_ylim()[1] == pytest.approx(5.0)


def test_placeholders_give_each_cell_its_fold_and_seed(tmp_path):
    """{fold} and {seed} in an override stand for the cell's held-out sequence and seed (a per-fold teacher); without
    folds, {fold} is a one-line PlanError naming study.folds."""
    extra = '\n[[camera]]\nname = "taught"\nset = ["loss.teacher=\\"teachers/{fold}/seed{seed}.safetensors\\""]\n'
    plan = load_plan(_plan_file(tmp_path, extra), FAST + ["study.seeds=[0,1]", "data.scene_sequences=2"])
    teachers = {(cell.fold, cell.seed): plan.config(cell, tmp_path).loss.teacher
                for cell in plan.cells() if cell.camera == "taught"}
    assert teachers == {(fold, seed): f"teachers/{fold}/seed{seed}.safetensors"
                        for fold in plan.sequences for seed in (0, 1)}
    assert {plan.config(cell, tmp_path).loss.teacher for cell in plan.cells() if cell.camera == "rggb"} == {""}
    with pytest.raises(PlanError, match=r"\{fold\} in a set .* study.folds = \"blocks\" or \"sequence\""):
        load_plan(_plan_file(tmp_path, extra), ["study.folds=none"])
