import json
import os

import numpy as np
import pytest
import torch

from warpsense.cli import main
from warpsense.config import load_config, with_overrides
from warpsense.data import build_dataset
from warpsense.models import count_parameters
from warpsense.system import build_system
from warpsense.system.checkpoint import CheckpointError, read_checkpoint, restore, save_checkpoint
from warpsense.train.engine import train
from warpsense.train.losses import segmentation_loss

TINY = ["data.scenes_train=16", "data.scenes_val=4", "data.batch_size=4", "data.scene_height=32",
        "data.scene_width=48", "data.crop_height=32", "data.crop_width=48", "train.plots=false", "train.compile=off",
        "train.cuda_graph=false"]


def test_model_parameter_budget():
    config = load_config()
    model = build_system(config, 11)
    assert count_parameters(model.network) <= 500_000
    assert model(torch.randint(0, 255, (1, 3, 30, 44), dtype=torch.uint8))[0].shape == (1, 11, 30, 44)


@pytest.mark.parametrize("preset,parameters", [("camvid_codesign", 336_267), ("camvid_fixed_isp", 334_011),
                                               ("camvid_rgb_teacher", 1_071_691)])
def test_presets_build_the_measured_networks(preset, parameters):
    """The camvid recipe's network (no squeeze-excitation, within the 0.5M budget) and the clean-RGB teacher as it
    was measured (val 0.7277: width 40 with squeeze-excitation, its width throughout), which must not follow the
    recipe's network changes (docs/results.md)."""
    config = load_config(preset, [])
    assert count_parameters(build_system(config, 11).network) == parameters


def test_overfits_a_fixed_batch():
    config = load_config(None, ["noise.enabled=false"])
    model = build_system(config, 11)
    dataset = build_dataset(config.data, "train", train=False)
    images = torch.stack([dataset[i][0][:, :32, :48] for i in range(4)])
    labels = torch.stack([dataset[i][1][:32, :48] for i in range(4)])
    optimizer = torch.optim.AdamW(model.parameters(), lr=5e-3)
    losses = []
    for _ in range(40):
        logits, sensed = model(images)
        loss, _ = segmentation_loss(logits, labels, sensed, config.loss)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


def test_train_then_eval_cli_on_scenes(tmp_path, capsys):
    config = load_config(None, TINY + ["train.epochs=2", "train.warmup_epochs=1", f"run.output_dir={tmp_path}"])
    run = train(config, progress=False)
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["phase"] for r in records] == ["warmup", "joint"] and "val_miou" in records[-1]
    # the process's setup before its first step, once: data within it, the first epoch's end after both
    first = records[0]
    assert 0 < first["setup_data_s"] <= first["setup_s"] < first["setup_s"] + first["epoch_time_s"] <= first["wall_s"]
    assert "setup_s" not in records[1]
    best_epoch = max(records, key=lambda r: r["val_miou"])["epoch"]  # the first of equal scores is kept
    summary = capsys.readouterr().out.strip().splitlines()[-3:]
    assert summary[0] == f"done: {run}"
    assert summary[1].startswith(f"  best: checkpoint_best.safetensors (epoch {best_epoch + 1}, val mIoU ")
    assert json.loads((run / "config.json").read_text())["train"]["epochs"] == 2
    out = tmp_path / "eval.json"
    assert main(["eval", "--checkpoint", str(run / "checkpoint_best.safetensors"), "--data", "scenes", "--split",
                 "val", "--limit", "4", "--json", str(out), "--device", "cpu", "--sweep", "--no-progress"]) == 0
    result = json.loads(out.read_text())
    assert {"miou", "per_class_iou", "pixel_accuracy", "num_images"} <= set(result) and result["num_images"] == 4
    assert {row["factor"] for row in result["sweep"]} == {"blur_sigma_px", "noise_scale", "bits"}
    # one factor moves at a time: the rows at the checkpoint's own operating point are the same evaluation
    at_operating_point = {row["miou"] for row in result["sweep"] if (row["factor"], row["value"]) in
                          {("blur_sigma_px", 0.0), ("noise_scale", 1.0), ("bits", config.quantize.bits)}}
    assert len(at_operating_point) == 1 and at_operating_point == {result["miou"]}
    capsys.readouterr()
    # without --data: the checkpoint's own dataset, named
    assert main(["eval", "--checkpoint", str(run / "checkpoint_last.safetensors"), "--limit", "2", "--device",
                 "cpu", "--json", str(out)]) == 0
    assert "dataset: scenes (the checkpoint's; --data picks another)" in capsys.readouterr().out
    assert json.loads(out.read_text())["dataset"] == "scenes"


def test_train_on_real_camvid_crops(shared_data, tmp_path, monkeypatch, capsys):
    config = load_config("camvid_codesign", TINY + [f"data.root={shared_data / 'camvid'}", "data.max_train_images=8",
                         "data.max_val_images=2", "train.epochs=1", "train.warmup_epochs=0", "optics.learnable=false",
                         f"run.output_dir={tmp_path}", "data.scale_min=0.25", "data.scale_max=0.3"])
    run = train(config, progress=False)
    record = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
    assert 0.0 <= record["val_miou"] <= 1.0 and record["train_loss"] > 0
    assert "selection_miou" not in record  # the protocol's default: all training images, judged on val
    # the final evaluation: val scored again at the last epoch, with per-image counts that sum to the totals
    evaluation = json.loads((run / "evaluation.json").read_text())
    assert list(evaluation["splits"]) == ["val"]
    val = evaluation["splits"]["val"]
    assert val["miou"] == pytest.approx(record["val_miou"]) and val["num_images"] == 2
    assert len(val["image_counts"]) == 2 and len(val["image_counts"][0]) == len(evaluation["class_names"])
    # the confusion matrix (rows: label, columns: prediction) holds the same pixels as the per-image counts
    confusion, counts = np.array(val["confusion"]), np.array(val["image_counts"]).sum(0)
    assert confusion.shape == (len(evaluation["class_names"]),) * 2 and confusion.sum() > 0
    np.testing.assert_array_equal(np.diag(confusion), counts[:, 0])
    np.testing.assert_array_equal(confusion.sum(0) - np.diag(confusion), counts[:, 1])
    np.testing.assert_array_equal(confusion.sum(1) - np.diag(confusion), counts[:, 2])
    # model selection on a held-out sequence (0006R0) stays an option, reported beside val
    held = train(with_overrides(config, ["data.holdout_prefix=0006R0", "run.name=held"]), progress=False)
    record = json.loads((held / "metrics.jsonl").read_text().splitlines()[-1])
    assert 0.0 <= record["selection_miou"] <= 1.0
    state = json.loads((held / "checkpoint_best.json").read_text())["state"]
    assert state["best_miou"] == record["selection_miou"]
    # `warpsense eval` with the checkpoint's own data: a split it trained on is scored with a note saying so
    from warpsense import system
    from warpsense.commands.eval import run_eval

    checkpoint = str(run / "checkpoint_last.safetensors")
    capsys.readouterr()
    run_eval(checkpoint, None, None, "train", device="cpu", limit=1, progress=False)
    assert "note: the checkpoint trained on train (data.train_split = 'train')" in capsys.readouterr().out
    run_eval(checkpoint, None, None, "val", device="cpu", limit=1, progress=False)
    assert "note:" not in capsys.readouterr().out
    # ... and one trained where its data.root was another folder asks for --data-root, in one line
    loaded = system.load_system

    def elsewhere(*args):
        model, moved, state = loaded(*args)
        moved.data.root = str(tmp_path / "training-machine" / "camvid")
        return model, moved, state

    monkeypatch.setattr(system, "load_system", elsewhere)
    with pytest.raises(ValueError, match=r"its data.root '.*training-machine/camvid' is not a folder here: pass "
                                         r"--data-root DIR \(the camvid folder\)$"):
        run_eval(checkpoint, None, None, "val", device="cpu", limit=1, progress=False)
    assert run_eval(checkpoint, None, str(shared_data / "camvid"), "val", device="cpu", limit=1,
                    progress=False)["num_images"] == 1


JITTER = ["data.jitter_stops=1.0", "data.jitter_gamma=0.3", "data.jitter_white_balance=0.1",
          "data.jitter_vignetting=0.3"]


@pytest.mark.parametrize("extra", [[], JITTER], ids=["plain", "jitter"])
def test_resume_continues_interrupted_run(tmp_path, extra):
    """An interrupted run resumed from its last checkpoint repeats the uninterrupted one (with the radiance jitter
    too: torch's generator is restored)."""
    base = TINY + ["train.epochs=3", "train.warmup_epochs=1", f"run.output_dir={tmp_path}"] + extra
    full = train(load_config(None, base + ["run.name=full"]), progress=False)
    expected = [json.loads(line) for line in (full / "metrics.jsonl").read_text().splitlines()]

    class Interrupt(Exception):
        pass

    import warpsense.train.engine as engine

    original = engine.save_checkpoint
    calls = {"n": 0}

    def save_then_die(path, *args, **kwargs):
        original(path, *args, **kwargs)
        if str(path).endswith("checkpoint_last.safetensors"):
            calls["n"] += 1
            if calls["n"] == 2:
                raise Interrupt

    engine.save_checkpoint = save_then_die
    try:
        with pytest.raises(Interrupt):
            train(load_config(None, base + ["run.name=cut"]), progress=False)
    finally:
        engine.save_checkpoint = original
    resumed = train(load_config(None, base + ["run.name=cut"]), resume=True, progress=False)
    got = [json.loads(line) for line in (resumed / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in got] == [0, 1, 2]
    assert ["setup_s" in r for r in got] == [True, False, True]  # each process's first epoch
    for a, b in zip(got, expected):
        assert a["train_loss"] == pytest.approx(b["train_loss"], rel=1e-5)
        assert a["val_miou"] == pytest.approx(b["val_miou"], abs=1e-6)


def test_resume_points_every_n_epochs(tmp_path, monkeypatch):
    """train.checkpoint_every = 2 writes the resume point after epochs 2 and 4 (the last) of 4; a run stopped in
    epoch 3, after its record was logged, resumes from epoch 2's point and drops epoch 3's record (that a resume
    repeats the uninterrupted run is test_resume_continues_interrupted_run's)."""
    import warpsense.train.engine as engine

    config = load_config(None, TINY + ["train.epochs=4", "train.warmup_epochs=1", "train.checkpoint_every=2",
                                       f"run.output_dir={tmp_path}", "run.name=cut"])
    written = []
    save_checkpoint, write_epoch = engine.save_checkpoint, engine._write_epoch

    def spy(path, model, config_dict, state, *args, **kwargs):
        save_checkpoint(path, model, config_dict, state, *args, **kwargs)
        if str(path).endswith("checkpoint_last.safetensors"):
            written.append(state["epoch"])

    def stop_in_epoch_3(run_dir, model, optimizer, config, state, *args, **kwargs):
        write_epoch(run_dir, model, optimizer, config, state, *args, **kwargs)
        if state["epoch"] == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(engine, "save_checkpoint", spy)
    monkeypatch.setattr(engine, "_write_epoch", stop_in_epoch_3)
    with pytest.raises(KeyboardInterrupt):
        train(config, progress=False)
    run = tmp_path / "cut"
    assert written == [1] and len((run / "metrics.jsonl").read_text().splitlines()) == 3
    monkeypatch.setattr(engine, "_write_epoch", write_epoch)
    train(config, resume=True, progress=False)
    assert written == [1, 3]
    got = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in got] == [0, 1, 2, 3]
    assert ["setup_s" in r for r in got] == [True, False, True, False]  # epoch 3 again, in the new process


def test_checkpoint_round_trip(tmp_path):
    config = load_config(None, ["optics.enabled=true", "optics.learnable=true"])
    model = build_system(config, 11)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.add_(torch.randn_like(parameter) * 0.01)
    save_checkpoint(tmp_path / "c.safetensors", model, config.to_dict(), {"epoch": 0})
    tensors, meta = read_checkpoint(tmp_path / "c.safetensors")
    clone = build_system(config, 11)
    restore(tensors, clone)
    for (name, a), (_, b) in zip(model.state_dict().items(), clone.state_dict().items()):
        assert torch.equal(a, b), name
    assert meta["config"]["optics"]["learnable"] is True
    assert not list(tmp_path.glob("*.tmp"))
    # a run folder or the readable .json copy named instead of the checkpoint: said so, with the file to name
    with pytest.raises(FileNotFoundError, match="is a folder; name its checkpoint file"):
        read_checkpoint(tmp_path)
    with pytest.raises(CheckpointError, match=r"c.json: the readable copy of a checkpoint; name .*c.safetensors"):
        read_checkpoint(tmp_path / "c.json")


def test_distillation_from_an_rgb_teacher(tmp_path):
    """An RGB teacher (model.input = srgb, no camera) trains with the project's own command; a RAW student distils
    it (the distillation term is recorded), its checkpoint holds the student alone and loads without the teacher."""
    from warpsense.system import load_system

    teacher_config = load_config(None, TINY + [
        "train.epochs=1", "train.warmup_epochs=0", f"run.output_dir={tmp_path}", "run.name=teacher",
        "model.input=srgb", "model.width=8", "optics.enabled=false", "exposure.enabled=false", "cfa.enabled=false",
        "noise.enabled=false", "quantize.enabled=false"])
    teacher_run = train(teacher_config, progress=False)
    teacher, _, _ = load_system(teacher_run / "checkpoint_last.safetensors", "cpu")
    assert teacher.network.stem[0].in_channels == 3 and not teacher.camera.stages()
    student_config = load_config(None, TINY + [
        "train.epochs=1", "train.warmup_epochs=0", f"run.output_dir={tmp_path}", "run.name=student",
        f"loss.teacher={teacher_run / 'checkpoint_last.safetensors'}", "loss.distill_weight=1.0"])
    student_run = train(student_config, progress=False)
    record = json.loads((student_run / "metrics.jsonl").read_text().splitlines()[-1])
    assert record["train_distill"] > 0
    tensors, _ = read_checkpoint(student_run / "checkpoint_last.safetensors")
    student = build_system(student_config, 4)
    assert {name[len("model."):] for name in tensors if name.startswith("model.")} == set(student.state_dict())
    (teacher_run / "checkpoint_last.safetensors").unlink()
    model, _, _ = load_system(student_run / "checkpoint_last.safetensors", "cpu")
    assert model.network.stem[0].in_channels == 1


def test_srgb_input_reads_the_frame_and_refuses_a_camera():
    from warpsense.config import ConfigError
    from warpsense.system import check_config

    off = ["optics.enabled=false", "exposure.enabled=false", "cfa.enabled=false", "noise.enabled=false",
           "quantize.enabled=false"]
    model = build_system(load_config(None, ["model.input=srgb", "model.width=4"] + off), 3)
    frame = torch.randint(0, 256, (1, 3, 16, 16), dtype=torch.uint8)
    torch.testing.assert_close(model.sense(frame), frame.float() / 255)
    with pytest.raises(ConfigError, match=r"model.input = \"srgb\".*disable cfa.enabled"):
        check_config(load_config(None, ["model.input=srgb"] + [o for o in off if not o.startswith("cfa")]))
    with pytest.raises(ConfigError, match="loss.distill_weight = 1.0 needs loss.teacher"):
        check_config(load_config(None, ["loss.distill_weight=1.0"]))


def test_context_module_trains_and_its_checkpoint_loads(tmp_path):
    """model.context = pyramid: the module trains (its BN scale leaves 0), the checkpoint's config rebuilds it, and
    the loaded model reproduces the run's recorded val mIoU."""
    from warpsense.models.dsunet import PyramidPooling
    from warpsense.system import load_system
    from warpsense.train.evaluate import evaluate

    config = load_config(None, TINY + ["train.epochs=2", "train.warmup_epochs=1", f"run.output_dir={tmp_path}",
                                       "model.context=pyramid"])
    run = train(config, progress=False)
    model, loaded_config, _ = load_system(run / "checkpoint_last.safetensors", "cpu")
    assert loaded_config.model.context == "pyramid"
    assert isinstance(model.network.context, PyramidPooling)
    assert model.network.context.norm.weight.abs().max() > 0
    val = build_dataset(config.data, "val", train=False)
    recorded = json.loads((run / "evaluation.json").read_text())["splits"]["val"]["miou"]
    assert evaluate(model, val, "cpu", batch_size=2)["miou"] == pytest.approx(recorded, abs=1e-9)


def test_run_deterministic_switches_torch_for_the_run_only(tmp_path, monkeypatch):
    """run.deterministic: the epochs run under torch's deterministic algorithms (warn-only) with cuDNN's
    deterministic convolutions and the cuBLAS workspace setting; the caller's settings come back afterwards."""
    from warpsense.train import engine

    seen = []
    run_epoch = engine._run_epoch

    def recording(*args, **kwargs):
        seen.append((torch.are_deterministic_algorithms_enabled(),
                     torch.is_deterministic_algorithms_warn_only_enabled(), torch.backends.cudnn.deterministic,
                     torch.backends.cudnn.benchmark, "CUBLAS_WORKSPACE_CONFIG" in os.environ))
        return run_epoch(*args, **kwargs)

    monkeypatch.setattr(engine, "_run_epoch", recording)
    monkeypatch.delenv("CUBLAS_WORKSPACE_CONFIG", raising=False)
    before = (torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.deterministic)
    config = load_config(None, TINY + ["train.epochs=1", "train.warmup_epochs=0", f"run.output_dir={tmp_path}",
                                       "run.deterministic=true"])
    train(config, progress=False)
    assert seen == [(True, True, True, False, True)]
    assert (torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.deterministic) == before
    assert json.loads((tmp_path / "default" / "config.json").read_text())["run"]["deterministic"] is True


@pytest.mark.cuda
def test_deterministic_runs_repeat_bitwise_on_cuda(tmp_path):
    """run.deterministic on CUDA: two runs with the same seed (DSUNet with the context pyramid, bf16 autocast, the
    learnable lens) end with bitwise-equal weights and equal losses. Without it DSUNet's upsampling backward alone
    makes two runs differ."""
    from warpsense.train.engine import train as train_run

    states, losses = [], []
    for name in ("a", "b"):
        config = load_config(None, TINY + ["train.epochs=2", "train.warmup_epochs=1", f"run.output_dir={tmp_path}",
                                           f"run.name={name}", "run.device=cuda", "run.deterministic=true",
                                           "model.context=pyramid", "optics.enabled=true", "optics.learnable=true"])
        run, model = train_run(config, progress=False, return_model=True)
        states.append({k: v.detach().cpu().clone() for k, v in model.state_dict().items()})
        losses.append([json.loads(line)["train_loss"] for line in (run / "metrics.jsonl").read_text().splitlines()])
    assert losses[0] == losses[1]
    for name in states[0]:
        assert torch.equal(states[0][name], states[1][name]), name


@pytest.mark.cuda
def test_captured_runs_report_their_capture_time_per_phase(tmp_path):
    """With train.cuda_graph each phase's first epoch captures the step: its record carries capture_s (host
    seconds, part of epoch_time_s); an epoch that replays does not."""
    config = load_config(None, TINY + ["train.epochs=3", "train.warmup_epochs=1", f"run.output_dir={tmp_path}",
                                       "run.device=cuda", "train.cuda_graph=true", "train.max_steps_per_epoch=4"])
    run = train(config, progress=False)
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["phase"] for r in records] == ["warmup", "joint", "joint"]
    for record in records[:2]:
        assert 0 < record["capture_s"] < record["epoch_time_s"]
    assert "capture_s" not in records[2]


@pytest.mark.parametrize("eval_batch, expected", [(0, 4), (3, 3)])
def test_validation_takes_train_eval_batch_size(tmp_path, monkeypatch, eval_batch, expected):
    """Validation and the final evaluation batch ``train.eval_batch_size`` images, the training batch when it is
    0; the metrics do not depend on it (eval-mode camera, noise seeded per image)."""
    from warpsense.train import engine, evaluate

    batches = []
    real = evaluate.evaluate

    def recording(model, dataset, device, batch_size=4, **kwargs):
        batches.append(batch_size)
        return real(model, dataset, device, batch_size, **kwargs)

    monkeypatch.setattr(engine, "evaluate", recording)
    config = load_config(None, TINY + ["train.epochs=1", "train.warmup_epochs=1", f"run.output_dir={tmp_path}",
                                       f"train.eval_batch_size={eval_batch}"])
    run = train(config, progress=False)
    assert batches and set(batches) == {expected}
    evaluation = json.loads((run / "evaluation.json").read_text())
    assert 0 <= evaluation["splits"]["val"]["miou"] <= 1



def test_a_run_folder_that_cannot_be_created_is_one_line_naming_the_key(tmp_path, monkeypatch, capsys):
    """A folder the process may not create (under /proc, another user's) was a bare "[Errno 13] ..." naming no
    key; the output folders made above it are removed."""
    import errno
    import pathlib

    from warpsense.cli import main

    real_mkdir = pathlib.Path.mkdir

    def refuse(self, *args, **kwargs):
        if self.name == "denied":  # its parents made first (as mkdir(parents=True) does), then the refusal
            real_mkdir(self.parent, parents=True, exist_ok=True)
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "mkdir", refuse)
    assert main(["train", "--set", f"run.output_dir={tmp_path / 'out'}", "--set", "run.name=denied",
                 "--set", "train.epochs=1", "--set", "train.warmup_epochs=0"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "run.output_dir" in err and "Permission denied" in err
    assert not (tmp_path / "out").exists()
