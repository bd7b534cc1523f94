"""Paths in a config (data.classes_file, data.root, optics.lens) are read from the working directory, and an error
for a missing one names the absolute path it looked at (configs/default.toml, data.root's comment)."""

from tests.reliability.conftest import assert_clean_failure

CLASSES = 'ignore = 255\n[[classes]]\nname = "road"\nid = 0\ncolor = [128, 64, 128]\n'


def test_a_missing_class_table_names_where_it_looked_and_the_one_in_the_dataset_folder(tmp_path, capsys,
                                                                                      monkeypatch):
    """Before: 'data.classes_file classes.toml: no such file', with no word of the folder it was looked for in
    (the working directory) nor of the table kept in the dataset folder."""
    work, data = tmp_path / "work", tmp_path / "work" / "mydata"
    data.mkdir(parents=True)
    (data / "classes.toml").write_text(CLASSES)
    monkeypatch.chdir(work)
    assert_clean_failure(capsys, ["train", "--set", "data.dataset=folder", "--set", "data.root=mydata", "--set",
                                  "data.classes_file=classes.toml", "--set", f"run.output_dir={tmp_path / 'runs'}"],
                         (f"data.classes_file classes.toml ({work / 'classes.toml'}): no such file",
                          "read from the working directory",
                          "the dataset folder has one: --set data.classes_file=mydata/classes.toml"),
                         watched=tmp_path)
    (data / "classes.toml").unlink()  # no table in the dataset folder either: no hint
    assert_clean_failure(capsys, ["train", "--set", "data.dataset=folder", "--set", "data.root=mydata", "--set",
                                  "data.classes_file=classes.toml", "--set", f"run.output_dir={tmp_path / 'runs'}"],
                         (f"({work / 'classes.toml'}): no such file",), watched=tmp_path)


def test_a_missing_split_list_and_lens_file_name_the_absolute_path(tmp_path, capsys, monkeypatch):
    """Before: 'nodata/train.txt: CamVid split list not found', 'optics.lens: mylens.json: cannot read'."""
    monkeypatch.chdir(tmp_path)
    assert_clean_failure(capsys, ["train", "--set", "data.dataset=camvid", "--set", "data.root=nodata", "--set",
                                  f"run.output_dir={tmp_path / 'runs'}"],
                         (f"nodata/train.txt ({tmp_path / 'nodata' / 'train.txt'}): CamVid split list not found",),
                         watched=tmp_path)
    assert_clean_failure(capsys, ["train", "--set", "optics.enabled=true", "--set", "optics.lens=mylens.json",
                                  "--set", f"run.output_dir={tmp_path / 'runs'}"],
                         (f"optics.lens: mylens.json ({tmp_path / 'mylens.json'}): cannot read",), watched=tmp_path)


def test_a_missing_teacher_checkpoint_names_the_absolute_path(tmp_path, capsys, monkeypatch):
    """Before: 't.safetensors: checkpoint not found'."""
    monkeypatch.chdir(tmp_path)
    assert_clean_failure(capsys, ["train", "--set", "loss.teacher=t.safetensors", "--set", "loss.distill_weight=0.5",
                                  "--set", "data.scenes_train=8", "--set", "data.scenes_val=4", "--set",
                                  f"run.output_dir={tmp_path / 'runs'}"],
                         (f"t.safetensors ({tmp_path / 't.safetensors'}): checkpoint not found",), watched=tmp_path)
