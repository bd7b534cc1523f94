"""`warpsense train`'s own checks before a run starts (warpsense/commands/train.py): train.cuda_graph on a machine
that trains on the CPU is refused before the run folder, the data or the model."""

import json

import pytest
import torch

from tests.reliability.conftest import assert_clean_failure
from warpsense.config import load_config
from warpsense.train import engine


@pytest.fixture
def cpu_only(monkeypatch):
    """No CUDA here, and no run may start: `engine.train` (what run_train calls after its checks) fails the test."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)

    def started(*args, **kwargs):
        raise AssertionError("the run started (run folder, data, model) before train.cuda_graph was refused")

    monkeypatch.setattr(engine, "train", started)


def test_a_cuda_graph_preset_on_a_cpu_is_refused_before_the_run_starts(tmp_path, capsys, cpu_only):
    """Before: `train --config camvid_codesign` on a CPU read the data, built the model and printed the run
    directory, then failed when the training step was set up ('train.cuda_graph needs a CUDA device; the model is
    on cpu')."""
    assert_clean_failure(capsys, ["train", "--config", "camvid_codesign", "--set", f"run.output_dir={tmp_path}"],
                         ("train.cuda_graph = true needs a CUDA device", "run.device = 'auto' is cpu",
                          "--set train.cuda_graph=false"), watched=tmp_path)


def test_a_continued_run_with_cuda_graph_is_refused_on_a_cpu_naming_its_config(tmp_path, capsys, cpu_only):
    run_dir = tmp_path / "camvid_codesign"
    run_dir.mkdir()
    (run_dir / "config.json").write_text(json.dumps(load_config("camvid_codesign").to_dict()))
    (run_dir / "checkpoint_last.safetensors").write_bytes(b"")
    assert_clean_failure(capsys, ["train", "--resume-dir", str(run_dir)],
                         (f"{run_dir / 'config.json'}: train.cuda_graph = true needs a CUDA device",),
                         watched=tmp_path)


def test_cuda_graph_off_on_a_cpu_goes_on_to_the_run(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    calls = []
    monkeypatch.setattr(engine, "train", lambda config, **kwargs: calls.append(config))
    from warpsense.cli import main

    assert main(["train", "--config", "camvid_codesign", "--set", "train.cuda_graph=false", "--set",
                 f"run.output_dir={tmp_path}"]) == 0
    assert len(calls) == 1 and calls[0].train.cuda_graph is False
