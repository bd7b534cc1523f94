"""data.dataset = "folder" (warpsense/data/folder.py): a CamVid-layout folder read with the user's class table."""

import json

import numpy as np
import pytest
from PIL import Image

from warpsense.config import load_config
from warpsense.data import DatasetError, FolderDataset, build_dataset, sequence_names
from warpsense.data.folder import read_class_table
from warpsense.data.labels import IGNORE_INDEX

TABLE = """ignore = 0
ignore_color = [0, 0, 0]
[[classes]]
name = "road"
id = 3
color = [128, 64, 128]
[[classes]]
name = "car"
id = 7
color = [64, 0, 128]
"""
IDS = {3: 0, 7: 1, 0: IGNORE_INDEX}  # label id -> the network's class index, written out by hand
COLOURS = {(128, 64, 128): 0, (64, 0, 128): 1, (0, 0, 0): IGNORE_INDEX}


def make_folder(root, label_values=(3, 7, 0), rgb_labels=False, frames=("seqA_0001", "seqA_0002", "seqB_0001")):
    """A CamVid-layout folder: train.txt and val.txt list 'image label' pairs; labels hold ``label_values``."""
    rng = np.random.default_rng(0)
    (root / "img").mkdir(parents=True)
    (root / "lab").mkdir()
    lines, expected = [], {}
    for name in frames:
        Image.fromarray(rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)).save(root / "img" / f"{name}.png")
        if rgb_labels:
            palette = list(COLOURS)
            choice = rng.integers(0, len(palette), (12, 16))
            label = np.array(palette, dtype=np.uint8)[choice]
            expected[name] = np.array([COLOURS[palette[c]] for c in choice.ravel()]).reshape(12, 16)
        else:
            label = rng.choice(np.array(label_values, dtype=np.uint8), (12, 16))
            expected[name] = np.vectorize(lambda v: IDS.get(int(v), -1))(label)
        Image.fromarray(label).save(root / "lab" / f"{name}.png")
        lines.append(f"img/{name}.png lab/{name}.png")
    (root / "train.txt").write_text("\n".join(lines[:2]) + "\n")
    (root / "val.txt").write_text(lines[2] + "\n")
    (root / "classes.toml").write_text(TABLE)
    return expected


def test_ids_map_to_the_tables_classes_in_its_order(tmp_path):
    expected = make_folder(tmp_path)
    dataset = FolderDataset(tmp_path, "train+val", classes_file=tmp_path / "classes.toml")
    assert dataset.classes == ("road", "car") and len(dataset) == 3
    for index, name in enumerate(["seqA_0001", "seqA_0002", "seqB_0001"]):
        image, label = dataset[index]
        assert image.shape == (3, 12, 16)
        np.testing.assert_array_equal(label.numpy(), expected[name])


def test_rgb_coded_labels_map_by_colour(tmp_path):
    expected = make_folder(tmp_path, rgb_labels=True)
    dataset = FolderDataset(tmp_path, "val", classes_file=tmp_path / "classes.toml")
    np.testing.assert_array_equal(dataset[0][1].numpy(), expected["seqB_0001"])
    assert (dataset[0][1] == IGNORE_INDEX).any() and (dataset[0][1] == 1).any()


def test_a_label_value_outside_the_table_names_the_file_value_and_table(tmp_path):
    make_folder(tmp_path, label_values=(3, 7, 12))
    dataset = FolderDataset(tmp_path, "train", classes_file=tmp_path / "classes.toml")
    with pytest.raises(DatasetError) as error:
        dataset[0]
    message = str(error.value)
    assert "lab/seqA_0001.png" in message and "value(s) 12" in message and "classes.toml" in message
    assert "ids 3, 7; ignore 0" in message


def test_an_unknown_colour_is_an_error_too(tmp_path):
    make_folder(tmp_path, rgb_labels=True)
    label = np.array(Image.open(tmp_path / "lab" / "seqB_0001.png"))
    label[0, 0] = (1, 2, 3)
    Image.fromarray(label).save(tmp_path / "lab" / "seqB_0001.png")
    with pytest.raises(DatasetError, match=r"seqB_0001.png: label colour\(s\) \(1,2,3\) not in the class table"):
        FolderDataset(tmp_path, "val", classes_file=tmp_path / "classes.toml")[0]


def test_json_table_equals_the_toml_one(tmp_path):
    make_folder(tmp_path)
    (tmp_path / "classes.json").write_text(json.dumps({
        "ignore": 0, "ignore_color": [0, 0, 0],
        "classes": [{"name": "road", "id": 3, "color": [128, 64, 128]},
                    {"name": "car", "id": 7, "color": [64, 0, 128]}]}))
    assert read_class_table(tmp_path / "classes.json").ids == read_class_table(tmp_path / "classes.toml").ids == (3, 7)


@pytest.mark.parametrize("table, message", [
    ('[[classes]]\nname = "a"\nid = 1\ncolor = [1, 2, 3]\n[[classes]]\nname = "b"\nid = 1\ncolor = [4, 5, 6]\n',
     "class ids must be distinct; repeated: 1"),
    ('ignore = 1\n[[classes]]\nname = "a"\nid = 1\ncolor = [1, 2, 3]\n', "the ignore id 1 is also the id of class 'a'"),
    ('[[classes]]\nname = "a"\nid = 1\n', "classes entry 1: expected exactly the keys name, id, color"),
    ('[[classes]]\nname = "a"\nid = 1\ncolor = [1, 2, 300]\n', "classes entry 1 (a) color: a colour is [r, g, b]"),
    ('[[classes]]\nname = "a"\nid = -1\ncolor = [1, 2, 3]\n', "classes entry 1 (a) id: a label id is an integer"),
    ('classes = []\n', "expected a non-empty list 'classes'"),
    ('colours = 1\n[[classes]]\nname = "a"\nid = 1\ncolor = [1, 2, 3]\n', "unknown key(s) colours"),
    ("classes = [\n", "cannot parse it"),
])
def test_a_bad_class_table_is_one_line_naming_the_file(tmp_path, table, message):
    (tmp_path / "t.toml").write_text(table)
    with pytest.raises(DatasetError) as error:
        read_class_table(tmp_path / "t.toml")
    assert message in str(error.value) and str(tmp_path / "t.toml") in str(error.value)
    assert len(str(error.value).splitlines()) == 1


def test_config_builds_it_and_sequence_folds_see_camvid_style_sequences(tmp_path):
    make_folder(tmp_path)
    data = load_config(None, ["data.dataset=folder", f"data.root={tmp_path}",
                              f"data.classes_file={tmp_path / 'classes.toml'}"]).data
    assert build_dataset(data, "val", train=False).classes == ("road", "car")
    assert sequence_names(data) == ["seqA", "seqB"]
    missing = load_config(None, ["data.dataset=folder", f"data.root={tmp_path}"]).data
    with pytest.raises(DatasetError, match="needs data.classes_file"):
        build_dataset(missing, "val", train=False)


def test_training_on_it_predicts_the_tables_classes(tmp_path):
    from safetensors import safe_open

    from warpsense.train import engine

    make_folder(tmp_path / "data")
    tiny = ["data.batch_size=2", "data.crop_height=8", "data.crop_width=8", "model.width=4", "train.epochs=1",
            "train.warmup_epochs=0", "train.max_steps_per_epoch=1", "train.plots=false", "train.amp=false"]
    config = load_config(None, [*tiny, "data.dataset=folder", f"data.root={tmp_path / 'data'}",
                                f"data.classes_file={tmp_path / 'data' / 'classes.toml'}",
                                f"run.output_dir={tmp_path / 'runs'}", "run.name=mine"])
    run_dir = engine.train(config, progress=False)
    checkpoint = next(run_dir.rglob("*.safetensors"))
    with safe_open(str(checkpoint), framework="pt") as handle:
        state = json.loads(handle.metadata()["warpsense"])["state"]
    assert state["num_classes"] == 2 and state["class_names"] == ["road", "car"]


def test_eval_finds_the_class_table_in_the_dataset_folder_from_anywhere(tmp_path, monkeypatch, capsys):
    """A run trained with a class table named relative to where it trained (data.classes_file = "classes.toml")
    is evaluated from another folder: eval finds the table under --data-root (the checkpoint's data.root); with no
    table there it is one line naming the field."""
    from warpsense.cli import main
    from warpsense.train import engine

    make_folder(tmp_path / "data")
    monkeypatch.chdir(tmp_path / "data")
    tiny = ["data.batch_size=2", "data.crop_height=8", "data.crop_width=8", "model.width=4", "train.epochs=1",
            "train.warmup_epochs=0", "train.max_steps_per_epoch=1", "train.plots=false", "train.amp=false"]
    config = load_config(None, [*tiny, "data.dataset=folder", "data.root=.", "data.classes_file=classes.toml",
                                f"run.output_dir={tmp_path / 'runs'}", "run.name=mine"])
    checkpoint = next(engine.train(config, progress=False).rglob("checkpoint_best.safetensors"))
    monkeypatch.chdir(tmp_path)
    assert main(["eval", "--checkpoint", str(checkpoint), "--data-root", str(tmp_path / "data"), "--device", "cpu",
                 "--no-progress"]) == 0
    assert "miou" in capsys.readouterr().out.lower()
    (tmp_path / "data" / "classes.toml").unlink()
    assert main(["eval", "--checkpoint", str(checkpoint), "--data-root", str(tmp_path / "data"), "--device",
                 "cpu"]) == 2
    error = capsys.readouterr().err
    assert "data.classes_file 'classes.toml'" in error and len(error.strip().splitlines()) == 1
