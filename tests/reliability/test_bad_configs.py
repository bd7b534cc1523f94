"""Config files and --set overrides: every key with a value of the wrong type, values out of range, unknown keys and
unreadable files. Each is refused at load, naming the file or option and the key, before any run folder exists."""

import dataclasses

import pytest

from tests.reliability.conftest import assert_clean_failure
from warpsense.config import Config

WRONG_VALUE = {bool: '"yes"', int: '"many"', float: '"x"', str: "5"}


def _keys():
    config = Config()
    for section in dataclasses.fields(config):
        values = getattr(config, section.name)
        for field in dataclasses.fields(values):
            yield section.name, field.name, type(getattr(values, field.name))


WRONG_TYPES = [pytest.param(section, key, WRONG_VALUE[kind], id=f"{section}.{key}") for section, key, kind in _keys()]


@pytest.mark.parametrize("section, key, value", WRONG_TYPES)
def test_wrong_type_in_a_config_file(section, key, value, tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(f"[{section}]\n{key} = {value}\n")
    assert_clean_failure(capsys, ["train", "--config", str(path), "--set", f"run.output_dir={tmp_path / 'runs'}"],
                         (str(path), f"{section}.{key}"), watched=tmp_path)


OUT_OF_RANGE = [
    "train.epochs=0", "train.epochs=-3", "train.lr=-0.1", "train.lr=inf", "train.lr=nan", "train.warmup_epochs=500",
    "train.eval_every=0", "train.checkpoint_every=0", "train.weight_decay=-1", "train.camera_grad_clip=-1",
    "train.time_budget_minutes=-1",
    "train.compile=fastest", "data.scale_min=2.0", "data.crop_height=0", "data.crop_width=-4", "data.batch_size=0",
    "data.num_workers=-1", "data.dataset=imagenet", "data.on_device=sometimes", "data.scenes_train=0",
    "loss.ohem_fraction=0", "loss.ohem_fraction=1.5", "loss.ohem_weight=-1", "cfa.temperature_end=0",
    "cfa.temperature_start=-1", "cfa.tile=0", "cfa.pattern=RGBX", "cfa.mode=learned", "quantize.bits=0",
    "quantize.bits=64", "quantize.white_level=0", "quantize.mode=min", "noise.shot=-0.1", "noise.read=nan",
    "noise.full_well_electrons=-5", "optics.method=magic", "optics.normalize_mean=-1", "optics.lens=no_such_lens",
    "model.width=0", "model.num_classes=-1", "model.name=resnet9000", "run.name=../escape", "run.name=",
    "run.device=tpu", "isp.gamma=0",
]


@pytest.mark.parametrize("override", OUT_OF_RANGE)
def test_value_out_of_range_is_refused_before_any_folder(override, tmp_path, capsys):
    key = override.split("=")[0]
    assert_clean_failure(capsys, ["train", "--set", override, "--set", f"run.output_dir={tmp_path / 'runs'}"],
                         (key,), watched=tmp_path)


@pytest.mark.parametrize("text, names", [
    ("[nonsense]\nkey = 1\n", ("nonsense",)),
    ("[train]\nlearning_rate = 0.1\n", ("train.learning_rate",)),
    ("[train\nlr = 0.1\n", ()),
    ("train = 3\n", ("train",)),
    ("base = \"no_such_preset\"\n", ("no_such_preset",)),
])
def test_malformed_config_files(text, names, tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert_clean_failure(capsys, ["train", "--config", str(path)], (str(path), *names), watched=tmp_path)


@pytest.mark.parametrize("text", ["", "# a comment only\n\n", "[train]\n[data]\n"])
def test_a_config_file_that_sets_nothing_is_an_error(text, tmp_path, capsys):
    """An empty file (the wrong file, or one not yet saved) was taken silently as all defaults; --print-config
    resolves the config without training, so a regression fails fast instead of starting a default run."""
    path = tmp_path / "empty.toml"
    path.write_text(text)
    assert_clean_failure(capsys, ["train", "--config", str(path), "--print-config"], (str(path), "sets no key"),
                         watched=tmp_path)


def test_unreadable_config_files(tmp_path, capsys):
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe[train]\n")
    assert_clean_failure(capsys, ["train", "--config", str(binary)], (str(binary),), watched=tmp_path)
    folder = tmp_path / "folder.toml"
    folder.mkdir()
    assert_clean_failure(capsys, ["train", "--config", str(folder)], (str(folder),), watched=tmp_path)
    assert_clean_failure(capsys, ["train", "--config", str(tmp_path / "missing.toml")], ("missing.toml",))
    assert_clean_failure(capsys, ["train", "--set", "train.lr"], ("train.lr",))


@pytest.mark.parametrize("overrides, names", [
    (["train.cuda_graph=true", "run.device=cpu"], ("cuda_graph",)),  # refused by the training step, after the folder
    (["data.dataset=camvid"], ("data.root",)),  # the dataset is looked for after the folder exists
])
def test_errors_found_after_the_run_folder_exists_leave_nothing(overrides, names, tmp_path, capsys):
    argv = ["train", "--set", f"run.output_dir={tmp_path / 'runs'}"]
    for override in overrides:
        argv += ["--set", override]
    assert_clean_failure(capsys, argv, names, watched=tmp_path)
    assert not (tmp_path / "runs" / "default").exists()
