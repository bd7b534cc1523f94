"""Continuing a run never loses it (issue 61): every check of a continuation (its config, a change of task, the files
it needs) runs before anything in the run is written, a refusal leaves every file of the run byte-identical, and a
continuation stopped before its first epoch is complete leaves the run as it was."""

import hashlib
import json
import shutil

import pytest

from warpsense.cli import main
from warpsense.config import load_config
from warpsense.train import engine
from warpsense.train.run_dir import LAST, is_task_key

TINY = ["data.scenes_train=4", "data.scenes_val=2", "data.batch_size=2", "data.scene_height=16",
        "data.scene_width=16", "data.crop_height=16", "data.crop_width=16", "model.width=4", "train.epochs=1",
        "train.warmup_epochs=0", "train.max_steps_per_epoch=1", "train.plots=false", "train.amp=false"]


def _snapshot(folder) -> dict[str, str]:
    """Every file under ``folder`` (relative path -> SHA-256 of its bytes) and every folder (-> "dir")."""
    return {str(path.relative_to(folder)): "dir" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
            for path in sorted(folder.rglob("*"))}


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A finished one-epoch run (copied per test by `run`)."""
    root = tmp_path_factory.mktemp("runs")
    return engine.train(load_config(None, [*TINY, f"run.output_dir={root}", "run.name=tiny"]), progress=False)


@pytest.fixture
def run(finished_run, tmp_path):
    copy = tmp_path / "tiny"
    shutil.copytree(finished_run, copy)
    return copy


def _refused(arguments, capsys, run) -> str:
    """Run `warpsense train` with ``arguments``; assert exit 2, one error line and the run unchanged; the line."""
    before = _snapshot(run)
    assert main(["train", *arguments, "--no-progress"]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("warpsense train: error: ") and "\n" not in error, error
    assert _snapshot(run) == before
    return error


TASK_CHANGES = {
    "dataset": (["data.dataset=camvid", "data.root=/nowhere/camvid"], "data.dataset: 'scenes' -> 'camvid'"),
    "root": (["data.root=/elsewhere"], "data.root: '' -> '/elsewhere'"),
    "val_split": (["data.val_split=train"], "data.val_split: 'val' -> 'train'"),
    "classes": (["model.num_classes=5"], "model.num_classes: 0 -> 5"),
    "network_width": (["model.width=8"], "model.width: 4 -> 8"),
    "network_context": (["model.context=pyramid"], "model.context: 'none' -> 'pyramid'"),
    "stage_off": (["noise.enabled=false"], "noise.enabled: True -> False"),
    "stage_on": (["optics.enabled=true"], "optics.enabled: False -> True"),
    "isp_on": (["isp.enabled=true"], "isp.enabled: False -> True"),
    "cfa_tile": (["cfa.tile=4"], "cfa.tile: 2 -> 4"),
    # the frames the run is judged on (issue 76; the class table: tests/train/test_inputs.py)
    "judged_frames": (["data.max_val_images=1"], "data.max_val_images: 0 -> 1"),
    "scenes_judged": (["data.scenes_val=3"], "data.scenes_val: 2 -> 3"),
    "scene_size": (["data.scene_height=32", "data.crop_height=32"], "data.scene_height: 16 -> 32"),
}


@pytest.mark.parametrize("case", list(TASK_CHANGES))
@pytest.mark.parametrize("how", ["extend", "allow_config_change"])
def test_a_change_of_task_is_refused_and_the_run_stays_byte_identical(run, capsys, case, how):
    overrides, change = TASK_CHANGES[case]
    flags = ["--extend", "1"] if how == "extend" else ["--allow-config-change"]
    sets = [part for text in overrides for part in ("--set", text)]
    error = _refused(["--resume-dir", str(run), *flags, *sets], capsys, run)
    assert change in error and "another task" in error and "new run" in error


def test_a_preset_that_is_another_task_is_refused_with_its_keys_named(run, capsys):
    # train.cuda_graph off: on a CPU the preset's CUDA graphs are refused first (tests/test_train_command.py)
    error = _refused(["--resume-dir", str(run), "--extend", "60", "--config", "camvid_codesign", "--set",
                      "train.cuda_graph=false"], capsys, run)
    assert "data.dataset: 'scenes' -> 'camvid'" in error and "another task" in error
    # with too few epochs for the preset's warm-up, the epochs --extend sets are named
    error = _refused(["--resume-dir", str(run), "--extend", "1", "--config", "camvid_codesign"], capsys, run)
    assert "train.warmup_epochs (45) must be <= train.epochs (2) (--extend 1: train.epochs = 1 trained + 1)" in error


@pytest.mark.parametrize("overrides, message", [
    (["train.lr=-1"], "train.lr: must be > 0"),  # the config's own checks
    (["train.warmup_epochs=5"], "train.warmup_epochs (5) must be <= train.epochs (2) (--extend 1: train.epochs = 1 "
                                "trained + 1)"),
    (["loss.distill_weight=1.0"], "loss.distill_weight = 1.0 needs loss.teacher"),  # the checks that need the stages
    (["optics.lens=/nowhere/lens.json"], "optics.lens"),  # a file it needs, checked while optics is off
    # a file it needs that only training opens: the teacher checkpoint
    (["loss.teacher=/nowhere/teacher.safetensors", "loss.distill_weight=1.0"], "/nowhere/teacher.safetensors"),
    (["no_such.key=1"], "unknown section [no_such]"),
])
def test_an_invalid_continuation_is_refused_before_anything_is_written(run, capsys, overrides, message):
    sets = [part for text in overrides for part in ("--set", text)]
    assert message in _refused(["--resume-dir", str(run), "--extend", "1", *sets], capsys, run)


def test_a_run_without_its_checkpoint_or_config_is_refused_unchanged(run, capsys):
    (run / LAST).unlink()
    assert "checkpoint_last.safetensors" in _refused(["--resume-dir", str(run), "--extend", "1"], capsys, run)
    assert "checkpoint_last.safetensors" in _refused(["--resume-dir", str(run)], capsys, run)


def test_a_damaged_config_is_refused_unchanged(run, capsys):
    (run / "config.json").write_text('{"train": {"epochs": ')
    assert "config.json: invalid JSON" in _refused(["--resume-dir", str(run), "--extend", "1"], capsys, run)


def _saved_with(run, **retired):
    """Write ``section__key=value`` entries into the run's config.json, as a run saved before those keys were
    retired holds them."""
    config = json.loads((run / "config.json").read_text())
    for dotted, value in retired.items():
        section, key = dotted.split("__")
        config[section][key] = value
    (run / "config.json").write_text(json.dumps(config))


def test_a_run_saved_with_a_retired_behaviour_is_refused_unchanged(run, capsys):
    _saved_with(run, loss__lovasz_stride=2)
    error = _refused(["--resume-dir", str(run), "--extend", "1"], capsys, run)
    assert error.endswith(f"loss.lovasz_stride = 2 was retired (the Lovasz term on every Nth pixel; measured, not "
                          f"adopted: docs/records/history.md); {run / 'config.json'} asks for it: read that run with "
                          "the warpsense version that made it")


def test_a_run_saved_with_retired_keys_at_todays_behaviour_continues(run, capsys):
    """The keys it held at the values of the behaviours that stayed are dropped: the continued run's config is
    today's, the first epochs' config stays as it was written."""
    _saved_with(run, loss__lovasz_stride=1, loss__class_balance=0.0, data__unprocess=False,
                model__decoder_join="concat", model__input_transform="linear", model__anscombe_offset=0.0059)
    original = (run / "config.json").read_text()
    assert main(["train", "--resume-dir", str(run), "--extend", "1", "--no-progress"]) == 0
    capsys.readouterr()
    continued = json.loads((run / "config.json").read_text())
    assert "lovasz_stride" not in continued["loss"] and "unprocess" not in continued["data"]
    assert continued["train"]["epochs"] == 2 and (run / "config.epoch1.json").read_text() == original


def test_a_continuation_stopped_in_its_first_epoch_leaves_the_run_as_it_was(run, monkeypatch, capsys):
    before = _snapshot(run)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(engine, "_run_epoch", interrupted)
    # a continuation that changes the config (not the task): config.json would be the first file it rewrites
    assert main(["train", "--resume-dir", str(run), "--extend", "1", "--set", "train.lr=0.001", "--no-progress"]) == 130
    assert "continue with: warpsense train --resume-dir" in capsys.readouterr().err
    assert _snapshot(run) == before


def test_a_continuation_that_diverges_in_its_first_epoch_leaves_the_run_as_it_was(run, monkeypatch):
    before = _snapshot(run)

    def diverged(model, statistics, epoch, run_dir):
        raise FloatingPointError(f"training diverged in epoch {epoch + 1}")

    monkeypatch.setattr(engine, "_check_finite", diverged)
    config = load_config(None, [*TINY, "train.epochs=2", f"run.output_dir={run.parent}", "run.name=tiny"])
    with pytest.raises(FloatingPointError, match="diverged in epoch 2"):
        engine.train(config, resume=run, progress=False, allow_config_change=True)
    assert _snapshot(run) == before


def test_the_config_of_the_first_epochs_is_never_overwritten(run, monkeypatch, capsys):
    original = (run / "config.json").read_text()
    write_epoch = engine._write_epoch

    def stop_after_epoch_2(run_dir, model, optimizer, config, state, *args, **kwargs):
        write_epoch(run_dir, model, optimizer, config, state, *args, **kwargs)
        raise KeyboardInterrupt

    # a continuation that completes epoch 2 without a resume point (every 3 epochs) and is stopped there
    monkeypatch.setattr(engine, "_write_epoch", stop_after_epoch_2)
    assert main(["train", "--resume-dir", str(run), "--extend", "3", "--set", "train.checkpoint_every=3",
                 "--no-progress"]) == 130
    assert (run / "config.epoch1.json").read_text() == original
    assert json.loads((run / "config.json").read_text())["train"]["epochs"] == 4
    monkeypatch.setattr(engine, "_write_epoch", write_epoch)
    # the next continuation starts from epoch 1's resume point again: the first config stays recorded
    assert main(["train", "--resume-dir", str(run), "--extend", "1", "--no-progress"]) == 0
    capsys.readouterr()
    assert (run / "config.epoch1.json").read_text() == original
    assert json.loads((run / "config.json").read_text())["train"]["epochs"] == 2
    assert [json.loads(line)["epoch"] for line in (run / "metrics.jsonl").read_text().splitlines()] == [0, 1]


def test_a_change_that_is_not_of_task_still_continues(run, capsys):
    assert main(["train", "--resume-dir", str(run), "--extend", "1", "--set", "train.lr=0.001", "--no-progress"]) == 0
    out = capsys.readouterr().out  # allowed by --extend, but said: each key, old -> new
    assert "config changes:" in out and "train.lr: 0.002 -> 0.001" in out and "train.epochs: 1 -> 2" in out
    assert json.loads((run / "config.json").read_text())["train"]["lr"] == 0.001
    assert json.loads((run / "config.epoch1.json").read_text())["train"]["lr"] == 0.002
    assert json.loads((run / "checkpoint_last.json").read_text())["state"]["epoch"] == 1


def test_task_keys():
    for key in ("data.dataset", "data.root", "model.num_classes", "model.width", "photons.enabled", "isp.enabled",
                "data.classes_file", "data.max_val_images"):
        assert is_task_key(key), key
    for key in ("train.lr", "train.epochs", "data.batch_size", "noise.shot", "run.device", "loss.teacher"):
        assert not is_task_key(key), key
