"""An interrupt between an epoch's metrics line and its resume checkpoint (issue 76): the best checkpoint that epoch
(or an earlier one) wrote is never deleted, nor replaced by a redone epoch that scored less. A new run stopped
before its first resume point keeps its best checkpoint (the folder was removed as 'nothing to resume'), a new run
of the same name goes to a new folder, and a study's cell trains again in its place with the attempt kept beside."""

import json

import pytest
import torch

from tests.train.test_continuations import TINY
from warpsense.cli import main
from warpsense.config import load_config
from warpsense.system.checkpoint import read_checkpoint
from warpsense.train import engine
from warpsense.train.run_dir import BEST, LAST, METRICS


def _interrupt_at_the_resume_point(monkeypatch, epoch: int = 0):
    """Ctrl-C as the resume checkpoint of ``epoch`` is written: after its metrics line and its best checkpoint."""
    save = engine.save_checkpoint

    def interrupted(path, model, config_dict, state, *args, **kwargs):
        if path.name == LAST and state["epoch"] == epoch:
            raise KeyboardInterrupt
        return save(path, model, config_dict, state, *args, **kwargs)

    monkeypatch.setattr(engine, "save_checkpoint", interrupted)


def test_a_new_run_stopped_before_its_resume_point_keeps_its_best_checkpoint(tmp_path, monkeypatch, capsys):
    _interrupt_at_the_resume_point(monkeypatch)
    arguments = ["train", *(part for text in TINY for part in ("--set", text)), "--set",
                 f"run.output_dir={tmp_path}", "--set", "run.name=cut", "--no-progress"]
    assert main(arguments) == 130
    run = tmp_path / "cut"
    error = capsys.readouterr().err.strip()
    assert error == (f"warpsense train: interrupted before the run's first resume point (train.checkpoint_every); "
                     f"nothing to resume, but its best checkpoint so far is kept: {run / BEST}; start the run again to "
                     "train it (in a new folder)")
    assert (run / BEST).is_file() and not (run / LAST).exists() and not list(run.glob("*.tmp"))
    tensors, meta = read_checkpoint(run / BEST)
    assert meta["state"]["epoch"] == 0
    assert [json.loads(line)["epoch"] for line in (run / METRICS).read_text().splitlines()] == [0]
    kept = (run / BEST).read_bytes()
    monkeypatch.undo()
    assert main(arguments) == 0  # a new run of the name: a new folder, the kept model untouched
    assert (tmp_path / "cut-2" / LAST).is_file() and (run / BEST).read_bytes() == kept


def test_a_resumed_run_never_replaces_its_best_checkpoint_with_a_redone_epoch_that_scored_less(tmp_path, monkeypatch):
    """Epoch 2 scored best (0.6) and wrote the best checkpoint, then Ctrl-C before its resume point: the resume
    redoes epoch 2 from epoch 1's point, whose best was 0.2; the redone epoch scored 0.4 (not bitwise repeatable
    on a GPU) and replaced the 0.6 checkpoint."""
    scores = iter([0.2, 0.6, 0.4])

    def validate(model, datasets, config, context, amp, progress):
        return {"val_miou": next(scores), "val_pixel_accuracy": 0.5, "val_per_class_iou": {}}

    monkeypatch.setattr(engine, "_validate", validate)
    save = engine.save_checkpoint
    _interrupt_at_the_resume_point(monkeypatch, epoch=1)
    config = load_config(None, [*TINY, "train.epochs=2", f"run.output_dir={tmp_path}", "run.name=cut"])
    with pytest.raises(engine.TrainingInterrupted):
        engine.train(config, progress=False)
    run = tmp_path / "cut"
    _, best = read_checkpoint(run / BEST)
    assert best["state"]["best_miou"] == 0.6 and best["state"]["epoch"] == 1
    weights = {name: tensor.clone() for name, tensor in read_checkpoint(run / BEST)[0].items()}
    monkeypatch.setattr(engine, "save_checkpoint", save)
    engine.train(None, resume=run, progress=False)
    tensors, best = read_checkpoint(run / BEST)
    assert best["state"]["best_miou"] == 0.6 and best["state"]["epoch"] == 1
    assert all(torch.equal(tensors[name], weights[name]) for name in weights)
    _, last = read_checkpoint(run / LAST)
    assert last["state"]["epoch"] == 1 and last["state"]["best_miou"] == 0.6


def test_a_study_cell_stopped_before_its_resume_point_trains_again_with_the_attempt_kept(tmp_path, monkeypatch,
                                                                                         capsys):
    from warpsense.study import load_plan, run_cells

    plan = load_plan("smoke", ["train.epochs=1", "train.warmup_epochs=0", "data.scenes_train=8",
                               "data.scenes_val=2", "train.eval_every=1", "model.width=4"])
    cell = plan.cells()[0]
    _interrupt_at_the_resume_point(monkeypatch)
    out = tmp_path / "study"
    assert run_cells(plan, out, [cell], record=False) == 130
    folder = out / "runs" / cell.run_name
    kept = (folder / BEST).read_bytes()
    monkeypatch.undo()
    capsys.readouterr()
    assert run_cells(plan, out, [cell], record=False) == 0
    assert f"kept in {folder.with_name(folder.name + '.interrupted')}" in capsys.readouterr().out
    assert (folder / "evaluation.json").is_file()
    assert (folder.with_name(folder.name + ".interrupted") / BEST).read_bytes() == kept
