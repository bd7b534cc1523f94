"""A continuation refuses files the run read that changed under the same path (issue 76): the run records the SHA-256
of its class table, split lists, lens file and teacher checkpoint (inputs.json), and `--resume-dir` / `--extend`
compare them before anything is written. A class table with two ids swapped was accepted and trained on."""

import hashlib
import shutil

import pytest

from tests.data.test_folder import make_folder
from warpsense.cli import main
from warpsense.config import ConfigError, load_config
from warpsense.resources import CONFIG_DIR
from warpsense.train import engine
from warpsense.train.inputs import INPUTS, check_inputs, input_digests, input_files, record_inputs

TINY = ["data.dataset=\"folder\"", "data.batch_size=2", "data.crop_height=12", "data.crop_width=16",
        "model.width=4", "train.epochs=1", "train.warmup_epochs=0", "train.max_steps_per_epoch=1",
        "train.plots=false", "train.amp=false"]


def _snapshot(folder) -> dict[str, str]:
    return {str(path.relative_to(folder)): "dir" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
            for path in sorted(folder.rglob("*"))}


@pytest.fixture(scope="module")
def finished_folder_run(tmp_path_factory):
    """A finished one-epoch run on a CamVid-layout folder with a class table of two classes (road id 3, car id 7)."""
    root = tmp_path_factory.mktemp("inputs")
    data = root / "data"
    make_folder(data)
    config = load_config(None, [*TINY, f"data.root=\"{data}\"", f"data.classes_file=\"{data / 'classes.toml'}\"",
                                f"run.output_dir=\"{root / 'runs'}\"", "run.name=folder"])
    return engine.train(config, progress=False), data


@pytest.fixture
def folder_run(finished_folder_run, tmp_path):
    """A copy of the finished run and its data (the run's config names the data's original place: restored after)."""
    run, data = finished_folder_run
    saved = {path: path.read_bytes() for path in data.rglob("*") if path.is_file()}
    copy = tmp_path / "folder"
    shutil.copytree(run, copy)
    yield copy, data
    for path, content in saved.items():
        path.write_bytes(content)


def test_the_run_records_what_it_read(folder_run):
    run, data = folder_run
    recorded = _inputs(run)
    assert set(recorded) == {str(data / "classes.toml"), str(data / "train.txt"), str(data / "val.txt")}
    assert recorded[str(data / "classes.toml")] == {
        "key": "data.classes_file", "sha256": hashlib.sha256((data / "classes.toml").read_bytes()).hexdigest()}


def _inputs(run) -> dict:
    import json

    return json.loads((run / INPUTS).read_text())["files"]


def _refused(capsys, run, *arguments) -> str:
    before = _snapshot(run)
    assert main(["train", "--resume-dir", str(run), *arguments, "--no-progress"]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("warpsense train: error: ") and "\n" not in error, error
    assert _snapshot(run) == before
    return error


def test_a_class_table_with_two_ids_swapped_is_refused_for_a_continuation(folder_run, capsys):
    run, data = folder_run
    table = data / "classes.toml"
    table.write_text(table.read_text().replace("id = 3", "id = 9").replace("id = 7", "id = 3").replace("id = 9",
                                                                                                       "id = 7"))
    error = _refused(capsys, run, "--extend", "1")
    assert f"{table} (data.classes_file): its content changed since {run} read it" in error
    assert "another task" in error and "new run" in error
    assert "its content changed" in _refused(capsys, run, "--extend", "1", "--set", "train.lr=0.001")


def test_another_class_table_is_another_task(folder_run, capsys, tmp_path):
    """data.classes_file naming another file (ids swapped in a copy): a change of task, refused by its key even with
    --extend, which allows other config changes."""
    run, data = folder_run
    other = tmp_path / "other.toml"
    other.write_text((data / "classes.toml").read_text().replace("id = 3", "id = 5"))
    error = _refused(capsys, run, "--extend", "1", "--set", f"data.classes_file={other}")
    assert f"data.classes_file: '{data / 'classes.toml'}' -> '{other}'" in error and "another task" in error


def test_an_edited_split_list_is_refused_for_a_continuation(folder_run, capsys):
    run, data = folder_run
    listing = data / "val.txt"
    listing.write_text(listing.read_text() + (data / "train.txt").read_text().splitlines()[0] + "\n")
    assert f"{listing} (data.root (folder split list)): its content changed" in _refused(capsys, run, "--extend", "1")


def test_unchanged_files_continue_and_the_continuation_records_them(folder_run, capsys):
    run, data = folder_run
    before = _inputs(run)
    assert main(["train", "--resume-dir", str(run), "--extend", "1", "--no-progress"]) == 0
    assert _inputs(run) == before


def test_a_run_recorded_before_inputs_were_continues(folder_run):
    """A run written before runs recorded their inputs has nothing to compare: it continues, and records them."""
    run, data = folder_run
    (run / INPUTS).unlink()
    check_inputs(run, load_config(None, [*TINY, f"data.root=\"{data}\"",
                                         f"data.classes_file=\"{data / 'classes.toml'}\""]))


@pytest.mark.parametrize("role", ["optics.lens", "loss.teacher"])
def test_a_changed_lens_file_or_teacher_is_named(tmp_path, role):
    """The files only some configs read: the lens file with the optics on, the teacher with distillation."""
    lens = tmp_path / "lens.json"
    shutil.copyfile(CONFIG_DIR / "lenses" / "phone_68deg.json", lens)
    teacher = tmp_path / "teacher.safetensors"
    teacher.write_bytes(b"weights")
    config = load_config(None, ["optics.enabled=true", f"optics.lens=\"{lens}\"", "loss.distill_weight=1.0",
                                f"loss.teacher=\"{teacher}\""])
    assert input_files(config) == {str(lens): "optics.lens", str(teacher): "loss.teacher"}
    assert input_files(load_config(None, [f"optics.lens=\"{lens}\"", f"loss.teacher=\"{teacher}\""])) == {}  # off
    record_inputs(tmp_path, input_digests(config))
    check_inputs(tmp_path, config)  # unchanged: continues
    changed = lens if role == "optics.lens" else teacher
    changed.write_bytes(changed.read_bytes() + b" ")
    with pytest.raises(ConfigError, match=f"{changed} \\({role}\\): its content changed since {tmp_path} read it"):
        check_inputs(tmp_path, config)


def test_a_damaged_inputs_record_is_named(tmp_path):
    (tmp_path / INPUTS).write_text('{"files": ')
    with pytest.raises(ConfigError, match=f"{tmp_path / INPUTS}: unreadable"):
        check_inputs(tmp_path, load_config(None, []))
    (tmp_path / INPUTS).write_text('{"files": {"a": 3}}')
    with pytest.raises(ConfigError, match=f"{tmp_path / INPUTS}: files: expected"):
        check_inputs(tmp_path, load_config(None, []))


def test_a_reused_run_whose_class_table_changed_is_not_copied(tmp_path, capsys):
    """`study run --reuse DIR` copies a finished run for a cell of the same config: one that read another content of
    the same class table trained another task, and is not copied (the cell trains on today's table)."""
    from warpsense.study import load_plan
    from warpsense.study.reuse import finished_runs, reuse_cells
    from warpsense.study.study_dir import evaluation_path, record_plan, run_dir

    data = tmp_path / "data"
    make_folder(data)
    plan_file = tmp_path / "plan.toml"
    sets = [*TINY, f"data.root=\"{data}\"", f"data.classes_file=\"{data / 'classes.toml'}\""]
    plan_file.write_text('[study]\nname = "p"\nbase = ""\nset = [' + ", ".join(repr(text) for text in sets)
                         + ']\nseeds = [0]\nreference = "a"\n[[camera]]\nname = "a"\n[[light]]\nname = "day"\n'
                         'full_well_electrons = 1000.0\nread_electrons = 1.0\nbits = 10\n')
    plan = load_plan(plan_file)
    source = tmp_path / "old"
    record_plan(plan, source)
    [cell] = plan.cells()
    config = plan.config(cell, source / "runs")
    run_dir(source, cell).mkdir(parents=True)
    config.save(run_dir(source, cell) / "config.json")
    evaluation_path(source, cell).write_text("{}")
    record_inputs(run_dir(source, cell), input_digests(config))
    table = data / "classes.toml"
    table.write_text(table.read_text().replace("id = 3", "id = 9"))
    out = tmp_path / "new"
    record_plan(plan, out)
    assert reuse_cells(plan, out, [cell], finished_runs([source])) == {}
    assert f"not copied for {cell.id}: {table} (data.classes_file): its content changed" in capsys.readouterr().out
    table.write_text(table.read_text().replace("id = 9", "id = 3"))
    assert reuse_cells(plan, out, [cell], finished_runs([source])) == {cell: run_dir(source, cell)}
