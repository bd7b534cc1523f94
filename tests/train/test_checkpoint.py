"""Checkpoints are one atomic file (issue 14, item 1) and every unreadable one is a one-line error naming it
(item 5)."""

import json
import os

import pytest
import torch
from safetensors.torch import save_file

from warpsense.cli import main
from warpsense.system import checkpoint
from warpsense.system.checkpoint import CheckpointError, read_checkpoint, save_checkpoint


def _model(value):
    model = torch.nn.Linear(2, 2)
    with torch.no_grad():
        model.weight.fill_(value)
    return model


def test_a_kill_after_the_tensors_land_keeps_a_consistent_checkpoint(tmp_path, monkeypatch):
    path = tmp_path / "checkpoint_last.safetensors"
    save_checkpoint(path, _model(0.0), {"run": {}}, {"epoch": 0})

    def killed(*args, **kwargs):
        raise KeyboardInterrupt  # the process dies after the checkpoint's rename, before the readable copy

    monkeypatch.setattr(checkpoint, "write_json", killed)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(path, _model(1.0), {"run": {}}, {"epoch": 1})
    assert json.loads(path.with_suffix(".json").read_text())["state"]["epoch"] == 0  # the stale copy
    tensors, meta = read_checkpoint(path)
    assert meta["state"]["epoch"] == 1 and torch.all(tensors["model.weight"] == 1.0)


def test_a_kill_before_the_rename_keeps_the_old_checkpoint(tmp_path, monkeypatch):
    path = tmp_path / "c.safetensors"
    save_checkpoint(path, _model(0.0), {}, {"epoch": 0})
    monkeypatch.setattr(os, "replace", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(path, _model(1.0), {}, {"epoch": 1})
    monkeypatch.undo()
    tensors, meta = read_checkpoint(path)
    assert meta["state"]["epoch"] == 0 and torch.all(tensors["model.weight"] == 0.0)


def _bad_files(tmp_path):
    good = tmp_path / "good.safetensors"
    save_checkpoint(good, _model(0.0), {}, {"epoch": 0})
    data = good.read_bytes()
    files = {"zero_byte": b"", "truncated": data[: len(data) // 2], "random": os.urandom(4096),
             "huge_header": (2**60).to_bytes(8, "little") + b"{}"}
    for name, content in files.items():
        (tmp_path / f"{name}.safetensors").write_bytes(content)
    torch.save({"model.weight": torch.zeros(2, 2)}, tmp_path / "pickle.safetensors")
    save_file({"model.weight": torch.zeros(2, 2)}, str(tmp_path / "list_meta.safetensors"),
              metadata={"warpsense": "[1, 2]"})
    save_file({"model.weight": torch.zeros(2, 2)}, str(tmp_path / "bad_json.safetensors"), metadata={"warpsense": "{"})
    save_file({"model.weight": torch.zeros(2, 2)}, str(tmp_path / "no_meta.safetensors"))
    save_file({"other": torch.zeros(2)}, str(tmp_path / "no_model.safetensors"),
              metadata={"warpsense": json.dumps({"config": {}, "state": {}})})
    return sorted(p for p in tmp_path.glob("*.safetensors") if p != good)


def test_every_unreadable_checkpoint_is_a_one_line_error(tmp_path, capsys):
    for path in _bad_files(tmp_path):
        with pytest.raises(CheckpointError, match=path.name):
            read_checkpoint(path)
        assert main(["eval", "--checkpoint", str(path), "--data", "scenes", "--device", "cpu"]) != 0
        error = capsys.readouterr().err.strip()
        assert path.name in error and "\n" not in error and "Traceback" not in error


def test_restored_optimizer_moments_keep_the_channels_last_layout(tmp_path):
    """The file stores contiguous tensors; restored AdamW moments take their parameter's NHWC strides again, and
    the resumed step equals the uninterrupted one."""
    def model_and_optimizer():
        torch.manual_seed(0)
        model = torch.nn.Conv2d(3, 4, 3).to(memory_format=torch.channels_last)
        return model, torch.optim.AdamW(model.parameters(), lr=0.1)

    def step(model, optimizer):
        optimizer.zero_grad()
        model(torch.ones(1, 3, 5, 5).contiguous(memory_format=torch.channels_last)).square().sum().backward()
        optimizer.step()

    model, optimizer = model_and_optimizer()
    step(model, optimizer)
    save_checkpoint(tmp_path / "c.safetensors", model, {}, {"epoch": 0}, optimizer)
    step(model, optimizer)
    resumed, resumed_optimizer = model_and_optimizer()
    tensors, _ = read_checkpoint(tmp_path / "c.safetensors")
    checkpoint.restore(tensors, resumed, resumed_optimizer)
    moment = resumed_optimizer.state[resumed.weight]["exp_avg"]
    assert moment.stride() == resumed.weight.stride() and resumed.weight.stride() != (27, 9, 3, 1)
    step(resumed, resumed_optimizer)
    torch.testing.assert_close(resumed.weight, model.weight)


def test_the_header_alone_holds_what_the_whole_checkpoint_holds(tmp_path):
    """read_header (a run's status, its kept best score) reads the metadata without the tensors: the same
    {"config", "state"} as read_checkpoint, and the same one-line error for every unreadable file it can tell."""
    (tmp_path / "run").mkdir()
    path = tmp_path / "run" / "c.safetensors"
    save_checkpoint(path, _model(0.5), {"run": {"name": "x"}}, {"epoch": 3, "best_miou": 0.25})
    assert checkpoint.read_header(path) == read_checkpoint(path)[1] == {
        "config": {"run": {"name": "x"}}, "state": {"epoch": 3, "best_miou": 0.25}}
    for bad in _bad_files(tmp_path):
        if bad.name == "no_model.safetensors":  # only the tensors tell: the header is a run's
            assert checkpoint.read_header(bad) == {"config": {}, "state": {}}
            continue
        with pytest.raises(CheckpointError) as whole:
            read_checkpoint(bad)
        with pytest.raises(CheckpointError) as header:
            checkpoint.read_header(bad)
        assert str(header.value) == str(whole.value)
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        checkpoint.read_header(tmp_path / "absent.safetensors")
