"""Fault injection (issue 14): every filesystem step that ends an epoch with a checkpoint to resume from (the
metrics line, the last checkpoint's tensors, mode and rename, its readable copy's text, mode and rename) fails in
turn; the run stops with that error, and resuming it then gives exactly the uninterrupted run: the same metrics and
the same final weights and optimizer state. (This tiny run's second epoch is not a new best, so the best
checkpoint's steps are not among them; they are the same `save_checkpoint`, covered in tests/train.)"""

import builtins
import json
import os

import pytest
import torch

from tests.train.test_training import TINY
from warpsense.config import load_config
from warpsense.system import checkpoint
from warpsense.train import engine, run_dir
from warpsense.train.engine import train

BASE = TINY + ["data.scenes_train=8", "data.scenes_val=4", "model.width=4", "train.epochs=3",
               "train.warmup_epochs=1"]


class Filesystem:
    """Counts (and on request fails) the filesystem calls that checkpointing and metrics make."""

    def __init__(self, monkeypatch, fail_at: int | None = None):
        self.calls, self.fail_at = [], fail_at
        real_replace, real_chmod, real_save, real_write = os.replace, os.chmod, checkpoint.save_file, \
            type(engine.Path()).write_text
        real_open = builtins.open

        def step(name, path, real, *args, **kwargs):
            self.calls.append((name, os.path.basename(str(path))))
            if len(self.calls) - 1 == self.fail_at:
                raise OSError(28, f"No space left on device (injected at {name} {path})")
            return real(*args, **kwargs)

        monkeypatch.setattr(os, "replace", lambda a, b: step("replace", b, real_replace, a, b))
        monkeypatch.setattr(os, "chmod", lambda p, m: step("chmod", p, real_chmod, p, m))
        monkeypatch.setattr(checkpoint, "save_file", lambda t, p, **k: step("save_file", p, real_save, t, p, **k))
        monkeypatch.setattr(type(engine.Path()), "write_text",
                            lambda self_, text, *a, **k: step("write_text", self_, real_write, self_, text, *a, **k))
        # the metrics line is appended by the run folder's owner
        monkeypatch.setattr(run_dir, "open", lambda p, mode="r", *a, **k: step("open", p, real_open, p, mode, *a, **k),
                            raising=False)


def _final(run):
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    tensors, _ = checkpoint.read_checkpoint(run / engine.LAST)
    return records, tensors


def _epoch_two_steps(monkeypatch, tmp_path):
    filesystem = Filesystem(monkeypatch)
    run = train(load_config(None, BASE + [f"run.output_dir={tmp_path}", "run.name=whole"]), progress=False)
    monkeypatch.undo()
    ends = [i for i, call in enumerate(filesystem.calls) if call == ("replace", "checkpoint_last.json")]
    return run, list(range(ends[0] + 1, ends[1] + 1)), filesystem.calls


def test_each_failing_filesystem_step_resumes_to_the_uninterrupted_run(monkeypatch, tmp_path):
    whole, steps, calls = _epoch_two_steps(monkeypatch, tmp_path)
    expected_records, expected_tensors = _final(whole)
    assert {calls[i][0] for i in steps} >= {"open", "save_file", "chmod", "replace", "write_text"}
    assert len(steps) >= 7
    for index in steps:
        name = f"cut{index}"
        Filesystem(monkeypatch, fail_at=index)
        with pytest.raises(OSError, match="injected"):
            train(load_config(None, BASE + [f"run.output_dir={tmp_path}", f"run.name={name}"]), progress=False)
        monkeypatch.undo()
        run = tmp_path / name
        assert not list(run.glob("*.tmp")), f"temporary left after a failure at {calls[index]}"
        resumed = train(None, resume=run, progress=False)
        records, tensors = _final(resumed)
        assert [r["epoch"] for r in records] == [0, 1, 2], calls[index]
        for got, want in zip(records, expected_records):
            assert got["train_loss"] == pytest.approx(want["train_loss"], rel=1e-6), calls[index]
            assert got["val_miou"] == pytest.approx(want["val_miou"], abs=1e-9), calls[index]
        for key, value in expected_tensors.items():
            assert torch.equal(tensors[key], value), (calls[index], key)
