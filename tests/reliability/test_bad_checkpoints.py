"""Checkpoints that cannot be used: unreadable files (zero-byte, truncated, random, a renamed pickle, a huge header,
missing or corrupt metadata), a config inside that is invalid, asks for a retired behaviour or points at a file
that is no lens, tensors that do not fit the model, missing state. `warpsense eval` and `warpsense train
--resume-dir` fail with one line naming the file, and resuming writes nothing into the run."""

import json

import torch
from safetensors.torch import save_file

from tests.reliability.conftest import assert_clean_failure
from tests.train.test_checkpoint import _bad_files
from warpsense.config import load_config
from warpsense.system import build_system
from warpsense.system.checkpoint import save_checkpoint


def _model_checkpoints(folder):
    """Readable checkpoints whose content is wrong for a model: (path, what the error names)."""
    config = load_config()
    model = build_system(config, 11)
    state = {"epoch": 0, "num_classes": 11}
    cases = []

    def write(name, config_dict, state_dict=state, tensors_model=model, names=()):
        path = folder / f"{name}.safetensors"
        save_checkpoint(path, tensors_model, config_dict, state_dict)
        cases.append((path, names))

    write("lens_is_not_a_lens", {**config.to_dict(), "optics": {**config.to_dict()["optics"], "enabled": True,
                                                               "lens": str(folder / "c.json")}}, names=("optics.lens",))
    (folder / "c.json").write_text("{\"psf_grid\": [1000, 1000]}")
    write("wrong_type_in_config", {**config.to_dict(), "train": {**config.to_dict()["train"], "lr": "fast"}},
          names=("train.lr",))
    write("unknown_section", {**config.to_dict(), "extra": {}}, names=("extra",))
    write("retired_behaviour", {**config.to_dict(), "loss": {**config.to_dict()["loss"], "class_balance": 0.5}},
          names=("loss.class_balance = 0.5 was retired", "docs/records/history.md"))
    write("retired_network", {**config.to_dict(), "model": {**config.to_dict()["model"], "name": "packunet"}},
          names=("model.name = 'packunet' was retired", "docs/records/history.md"))
    write("no_num_classes", config.to_dict(), state_dict={"epoch": 0}, names=("num_classes",))
    write("other_width", config.to_dict(), tensors_model=build_system(load_config(None, ["model.width=4"]), 11),
          names=("model",))
    write("other_classes", config.to_dict(), state_dict={"epoch": 0, "num_classes": 5}, names=("model",))
    save_file({"model.x": torch.zeros(1)}, str(folder / "state_not_object.safetensors"),
              metadata={"warpsense": json.dumps({"config": config.to_dict(), "state": []})})
    cases.append((folder / "state_not_object.safetensors", ()))
    return cases


def _all(folder):
    return [(path, ()) for path in _bad_files(folder)] + _model_checkpoints(folder)


def test_eval_refuses_every_bad_checkpoint(tmp_path, capsys):
    cases = _all(tmp_path)
    assert len(cases) >= 15
    for path, names in cases:
        assert_clean_failure(capsys, ["eval", "--checkpoint", str(path), "--data", "scenes", "--device", "cpu"],
                             (path.name, *names))


def test_resume_refuses_every_bad_checkpoint(tmp_path, capsys):
    config = load_config()
    (tmp_path / "files").mkdir()
    for path, _names in _all(tmp_path / "files"):
        run = tmp_path / f"run-{path.stem}"
        run.mkdir()
        (run / "config.json").write_text(json.dumps(config.to_dict()))
        (run / "checkpoint_last.safetensors").write_bytes(path.read_bytes())
        assert_clean_failure(capsys, ["train", "--resume-dir", str(run), "--no-progress"],
                             ("checkpoint_last.safetensors",), watched=run)
