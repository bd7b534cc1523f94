import json
import subprocess
import sys

import pytest

import warpsense
from warpsense.cli import build_parser, main


def test_import_and_version(capsys):
    assert warpsense.__version__
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert warpsense.__version__ in capsys.readouterr().out


def test_help_lists_commands(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for command in ("train", "eval", "bench", "convert", "predict"):
        assert command in out


@pytest.mark.parametrize("command,option", [("train", "--set"), ("eval", "--checkpoint"), ("bench", "--quick"),
                                            ("convert", "--out"), ("predict", "--out")])
def test_subcommand_help_documents_options(capsys, command, option):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    assert option in capsys.readouterr().out


def test_bad_config_is_one_line_error_nonzero(capsys):
    assert main(["train", "--set", "train.epoch=1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("warpsense train: error:") and "train.epoch" in err and "\n" not in err


def test_console_entry_point_runs():
    result = subprocess.run([sys.executable, "-m", "warpsense", "--help"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and "convert" in result.stdout
    assert build_parser().prog == "warpsense"


@pytest.mark.parametrize("arguments,message", [
    (["--plot", "x.png"], "--plot draws the sweeps: add --sweep"),
    (["--latency", "--latency-size", "192"], "--latency-size must be HxW"),
    # without --latency these were ignored: a full evaluation ran, with no latency in it
    (["--latency-size", "64x96"], "--latency-size sets the input of --latency: add --latency"),
    (["--latency-batch", "2"], "--latency-batch sets the input of --latency: add --latency"),
])
def test_eval_argument_mistakes_are_one_line_errors_before_any_work(capsys, arguments, message):
    assert main(["eval", "--checkpoint", "missing.safetensors", *arguments]) == 2
    assert message in capsys.readouterr().err


def test_building_the_parser_loads_no_torch():
    """Every `warpsense` call builds every command's parser: the command modules import their work (torch, Warp)
    when it runs, so --help stays quick and `main` sets the OpenMP defaults before torch loads."""
    code = "import sys; from warpsense.cli import build_parser; build_parser(); print('torch' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.stdout.strip() == "False", result.stderr


def test_subpackages_load_on_attribute_access_and_no_driver_warning_on_cpu():
    code = "import warpsense; print(warpsense.ops.cfa_mosaic.__name__)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.stdout.strip() == "cfa_mosaic"
    import torch

    if not torch.cuda.is_available():
        assert "CUDA driver" not in result.stderr


def test_train_print_config_shows_the_resolved_config_and_trains_nothing(tmp_path, capsys):
    assert main(["train", "--config", "camvid_codesign", "--set", "train.epochs=60",
                 "--set", f"run.output_dir={tmp_path}", "--print-config"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["train"]["epochs"] == 60 and printed["optics"]["learnable"] is True  # override and preset
    assert printed["model"]["width"] == 24 and list(tmp_path.iterdir()) == []  # from the base preset; no run


def test_unavailable_device_and_missing_capture_are_one_line_errors(tmp_path, capsys, monkeypatch):
    import torch

    from tests.reliability.conftest import assert_clean_failure

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert_clean_failure(capsys, ["train", "--set", "run.device=cuda", "--set", f"run.output_dir={tmp_path}"],
                         ("device cuda", "use cpu or auto", "run.device"))
    assert_clean_failure(capsys, ["predict", "checkpoints/camvid_codesign.safetensors", str(tmp_path / "no.dng"),
                                  "--out", str(tmp_path / "p.png"), "--device", "cpu"], ("no.dng", "no such file"),
                         watched=tmp_path)


@pytest.mark.parametrize("command", ["eval", "bench", "predict", "study"])
def test_help_shows_every_default(command):
    import argparse

    parser = build_parser()
    subcommands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    parsers = [subcommands[command]]
    if command == "study":
        parsers = list(next(a for a in parsers[0]._actions if isinstance(a, argparse._SubParsersAction)).choices
                       .values())
    for sub in parsers:
        for action in sub._actions:
            if action.default not in (None, False, [], argparse.SUPPRESS) and action.help:
                assert "default" in action.help, (command, action.dest)


def test_eval_flip_tta_is_recorded_and_scored(shared_data, tmp_path, capsys):
    """`warpsense eval --flip-tta` on the committed checkpoint: the JSON says so, and its mIoU is the model's
    prediction averaged with the mirrored capture's (SensingModel.probabilities with flip)."""
    import torch

    from warpsense.data import build_dataset
    from warpsense.system import load_system
    from warpsense.train.metrics import ConfusionMatrix

    out = tmp_path / "eval.json"
    checkpoint = "checkpoints/camvid_codesign.safetensors"
    assert main(["eval", "--checkpoint", checkpoint, "--data-root", str(shared_data / "camvid"), "--limit", "1",
                 "--device", "cpu", "--flip-tta", "--json", str(out), "--no-progress"]) == 0
    payload = json.loads(out.read_text())
    assert payload["flip_tta"] is True and payload["num_images"] == 1
    model, config, _ = load_system(checkpoint, "cpu")
    config.data.root, config.data.max_val_images = str(shared_data / "camvid"), 1
    image, label = build_dataset(config.data, "val", train=False, seed=config.run.seed)[0][:2]
    model.eval()
    matrix = ConfusionMatrix(model.network.head.out_channels, "cpu")
    matrix.update(model.probabilities(image[None], image_index=torch.tensor([0]), flip=True).argmax(1), label[None])
    assert payload["miou"] == pytest.approx(matrix.compute()["miou"], abs=1e-12)


@pytest.mark.parametrize("option,value,message", [
    ("--limit", "-3", "argument --limit: must be >= 0, got -3"),
    ("--latency-batch", "0", "argument --latency-batch: must be >= 1, got 0"),
    ("--batch-size", "0", "argument --batch-size: must be >= 1, got 0"),
    ("--batch-size", "two", "argument --batch-size: expected an integer, got 'two'"),
])
def test_eval_counts_out_of_range_are_usage_errors_naming_the_option(capsys, option, value, message):
    """A negative --limit used to drop images from the end, and a zero batch failed deep in psf_conv or torch's
    DataLoader after the data had loaded: the parser refuses them, before the (here missing) checkpoint is read."""
    with pytest.raises(SystemExit) as exit_info:
        main(["eval", "--checkpoint", "missing.safetensors", option, value])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


def _untrained_checkpoint(path, overrides, num_classes):
    """An untrained model saved as `warpsense train` saves one, trained on CamVid's classes (what the label checks
    read: the config's dataset, state.num_classes and state.class_names)."""
    from warpsense.config import load_config
    from warpsense.data.labels import CAMVID_CLASSES
    from warpsense.system import build_system, save_checkpoint

    config = load_config(None, ["data.scene_height=32", "data.scene_width=48", *overrides])
    state = {"epoch": 0, "step": 1, "best_miou": 0.0, "num_classes": num_classes, "class_names": list(CAMVID_CLASSES)}
    save_checkpoint(path, build_system(config, num_classes), config.to_dict(), state)
    return str(path)


def test_eval_refuses_a_checkpoint_predicting_other_classes_than_the_dataset(tmp_path, capsys):
    """A run trained with model.num_classes=19 on 11-class data used to score on 11-class scenes with rc 0 (a
    19-class mIoU listing 11 names): refused in one line naming both counts."""
    from tests.reliability.conftest import assert_clean_failure

    checkpoint = _untrained_checkpoint(tmp_path / "c19.safetensors", ["model.num_classes=19"], 19)
    assert_clean_failure(capsys, ["eval", "--checkpoint", checkpoint, "--limit", "1", "--device", "cpu",
                                  "--no-progress", "--json", str(tmp_path / "e.json")],
                         ("c19.safetensors", "predicts 19 classes", "scenes labels 11"), watched=tmp_path)


def test_eval_on_another_dataset_than_the_checkpoints_says_so(tmp_path, capsys):
    """A checkpoint scored on a dataset it was not trained on (same classes) runs, with a note and the dataset it
    was trained on in the JSON, instead of silently."""
    checkpoint = _untrained_checkpoint(tmp_path / "cv.safetensors", ["data.dataset=camvid", "data.root=/nowhere"], 11)
    out = tmp_path / "e.json"
    assert main(["eval", "--checkpoint", checkpoint, "--data", "scenes", "--limit", "1", "--device", "cpu",
                 "--no-progress", "--json", str(out)]) == 0
    assert "note: the checkpoint was trained on camvid; scoring it on scenes" in capsys.readouterr().out
    payload = json.loads(out.read_text())
    assert payload["dataset"] == "scenes" and payload["trained_on"] == "camvid"


@pytest.mark.parametrize("terminal", [False, True])
def test_progress_bars_are_drawn_on_a_terminal_only(tmp_path, capsys, monkeypatch, terminal):
    """Bars redrawn with carriage returns went into log files (36 KB for a 2-minute run): without --no-progress
    they are drawn when stderr is a terminal, and not otherwise."""
    import numpy as np

    from warpsense.data.raw import write_dng

    write_dng(tmp_path / "frame.dng", np.random.default_rng(0).random((32, 48)), "RGGB", black_level=64,
              white_level=1023)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: terminal)
    assert main(["convert", str(tmp_path / "frame.dng"), "--out", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()
    assert ("convert: 100%" in captured.err) is terminal and ("\r" in captured.err) is terminal
    assert "converted 1 of 1 file(s)" in captured.out


def test_ctrl_c_message_starts_on_its_own_line(tmp_path, capsys, monkeypatch):
    """The epoch's bar is left mid-line when Ctrl-C stops training: the message that says how to continue must not
    be glued onto it."""
    import warpsense.commands.train as train_command
    from warpsense.train import engine
    from warpsense.train.engine import TrainingInterrupted

    def interrupted_mid_epoch(config, **kwargs):
        sys.stderr.write("\repoch 2/3 (joint):  40%|####      | 2/5")  # what tqdm leaves
        raise TrainingInterrupted(tmp_path)

    (tmp_path / "checkpoint_last.safetensors").write_bytes(b"")
    monkeypatch.setattr(engine, "train", interrupted_mid_epoch)  # run_train imports it when it runs
    assert train_command.run_train(None, [f"run.output_dir={tmp_path}"], progress=True) == 130
    lines = capsys.readouterr().err.splitlines()
    assert lines[-1] == f"warpsense train: interrupted; continue with: warpsense train --resume-dir {tmp_path}"


def test_predict_reports_sizes_height_by_width(tmp_path, capsys):
    """predict printed width x height ("1734x1156") while --latency-size and the docs take height x width: one
    convention, HxW, on a capture that is wider than tall."""
    import numpy as np

    from warpsense.data.raw import write_dng

    checkpoint = _untrained_checkpoint(tmp_path / "bayer.safetensors", ["cfa.mode=fixed", "cfa.pattern=RGGB"], 11)
    write_dng(tmp_path / "wide.dng", np.random.default_rng(0).random((32, 64)), "RGGB", black_level=64,
              white_level=1023)
    assert main(["predict", checkpoint, str(tmp_path / "wide.dng"), "--out", str(tmp_path / "p.png"), "--device",
                 "cpu", "--no-legend"]) == 0
    out = capsys.readouterr().out
    assert "(32x64 HxW; the network ran at " in out, out
    ran_at = out.split("the network ran at ")[1].split(",")[0]
    height, width = (int(n) for n in ran_at.split("x"))
    assert width == 2 * height  # the network's input keeps the capture's aspect: HxW too


def _options(parser) -> list[str]:
    import argparse

    return [action.option_strings[-1] for action in parser._actions
            if action.option_strings and action.help != argparse.SUPPRESS
            and not isinstance(action, argparse._HelpAction)]


def test_readme_usage_block_names_every_option():
    """The README's usage block left out --print-config, --no-progress, --allow-config-change, predict's --overlay
    and --no-legend, study's --reuse, --progress and --resamples, and showed eval's optional --data, --data-root and
    --split as required: each command's line names every option its parser has (study: those the issue named, its
    owners keep the rest), and eval's optional ones in brackets."""
    import argparse
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    usage = readme.split("## Usage", 1)[1].split("```")[1]
    lines = {}
    for line in usage.splitlines():
        words = line.split()
        if words[:1] == ["warpsense"]:
            lines[" ".join(words[1:3]) if words[1] == "study" else words[1]] = line
    subcommands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    for command in ("train", "eval", "bench", "convert", "predict", "lens"):
        missing = [option for option in _options(subcommands[command]) if option not in lines[command]]
        assert not missing, (command, missing)
    assert all(option in lines["study run"] for option in ("--reuse", "--progress"))
    assert "--resamples" in lines["study report"]
    for option in ("--data {", "--data-root", "--split"):
        assert f"[{option}" in lines["eval"], option


def test_eval_help_does_not_ask_for_the_json_beside_the_checkpoint(capsys):
    """The checkpoint's config and classes are in its metadata (`read_checkpoint`): eval --help said it needed "its
    .json beside it", which it does not."""
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "with its .json beside it" not in text and "the .json beside it is a readable copy, not needed" in text


@pytest.mark.parametrize("inherited,policy,spins", [(None, "PASSIVE", "0"), ("ACTIVE", "ACTIVE", "30000000000")])
def test_commands_load_torch_with_openmp_threads_that_sleep_when_idle(inherited, policy, spins):
    """Beside another CPU job the quickstart's training ran 14x slower: libgomp's idle threads spin at each barrier
    (300000 turns when the policy is unset) and take the cores from those with work. A command's process loads
    torch's OpenMP runtime with OMP_WAIT_POLICY=PASSIVE (no spinning) unless the caller set the policy.
    OMP_DISPLAY_ENV=VERBOSE makes the runtime print what it read: its OMP_WAIT_POLICY line says PASSIVE when unset
    too, its GOMP_SPINCOUNT line tells them apart."""
    import os

    environment = {key: value for key, value in os.environ.items() if key not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    environment["OMP_DISPLAY_ENV"] = "VERBOSE"
    if inherited:
        environment["OMP_WAIT_POLICY"] = inherited
    result = subprocess.run([sys.executable, "-m", "warpsense", "eval", "--checkpoint", "missing.safetensors"],
                            capture_output=True, text=True, timeout=120, env=environment)
    assert result.returncode == 2 and "missing.safetensors" in result.stderr
    if "GOMP_SPINCOUNT" not in result.stderr:
        pytest.skip("torch's OpenMP runtime here is not libgomp (no GOMP_SPINCOUNT in its OMP_DISPLAY_ENV)")
    assert f"OMP_WAIT_POLICY = '{policy}'" in result.stderr and f"GOMP_SPINCOUNT = '{spins}'" in result.stderr


def test_load_system_takes_a_device_name_and_refuses_cuda_without_it_in_one_line(monkeypatch):
    """The Python API's load_system(path, "cuda") on a machine without CUDA said only torch's bare
    "AssertionError: Torch not compiled with CUDA enabled"; a device name is resolved as the commands do."""
    import torch

    from warpsense.system import load_system

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for device in ("cuda", torch.device("cuda")):
        with pytest.raises(ValueError, match="device cuda: .* use cpu or auto"):
            load_system("checkpoints/camvid_codesign.safetensors", device)
    model, _, _ = load_system("checkpoints/camvid_codesign.safetensors", "auto")
    assert next(model.parameters()).device.type == "cpu"


def test_allow_config_change_without_a_run_to_continue_is_one_line_error(tmp_path, capsys):
    """--allow-config-change without --resume/--resume-dir was ignored and a fresh run trained (--extend, its
    sibling, was refused): a one-line error before anything is written."""
    from tests.reliability.conftest import assert_clean_failure

    assert_clean_failure(capsys, ["train", "--allow-config-change", "--set", f"run.output_dir={tmp_path}",
                                  "--set", "train.epochs=1", "--set", "train.warmup_epochs=0", "--no-progress"],
                         ("--allow-config-change", "--resume"), watched=tmp_path)


@pytest.mark.parametrize("suite", ["kernels", "train"])
def test_bench_camvid_for_a_suite_that_reads_none_is_one_line_error(capsys, suite):
    """--camvid with the kernels or train suite was checked (its val.txt read) and then ignored."""
    from tests.reliability.conftest import assert_clean_failure

    assert_clean_failure(capsys, ["bench", "--suite", suite, "--camvid", "camvid_root", "--quick"],
                         ("--camvid", f"--suite {suite}"))


def test_a_bad_training_image_read_by_a_dataloader_worker_is_one_line_error(tmp_path, capsys):
    """With data.num_workers > 0 the worker's error came back with its traceback as the message: the "one-line"
    error was some twenty lines of it."""
    import numpy as np
    from PIL import Image

    from tests.reliability.conftest import assert_clean_failure

    root = tmp_path / "camvid"
    for split, frames in (("train", ["0001TP_000010", "0001TP_000020"]), ("val", ["0016E5_000010"])):
        (root / split).mkdir(parents=True)
        (root / f"{split}annot").mkdir()
        for frame in frames:
            Image.fromarray(np.zeros((32, 48, 3), dtype=np.uint8)).save(root / split / f"{frame}.png")
            Image.fromarray(np.full((32, 48), 3, dtype=np.uint8)).save(root / f"{split}annot" / f"{frame}.png")
        (root / f"{split}.txt").write_text("".join(f"{split}/{f}.png {split}annot/{f}.png\n" for f in frames))
    bad = root / "train" / "0001TP_000020.png"
    bad.write_bytes(bad.read_bytes()[:60])  # the header opens; the pixel data is cut off
    settings = ["data.dataset=camvid", f"data.root={root}", "data.num_workers=1", "data.batch_size=2",
                "data.crop_height=32", "data.crop_width=48", "train.epochs=1", "train.warmup_epochs=0",
                "train.plots=false", "train.compile=off", "train.cuda_graph=false", "run.device=cpu",
                f"run.output_dir={tmp_path / 'runs'}"]
    assert_clean_failure(capsys, ["train", "--no-progress", *(f"--set={text}" for text in settings)],
                         (f"{bad}: unreadable image",))


TERM_RUN = ["data.scenes_train=16", "data.scenes_val=4", "data.batch_size=4", "data.scene_height=32",
            "data.scene_width=48", "data.crop_height=32", "data.crop_width=48", "train.plots=false",
            "train.compile=off", "train.cuda_graph=false", "train.epochs=3", "train.warmup_epochs=1"]


def _train_command(tmp_path, *flags):
    return ["train", *(part for text in TERM_RUN for part in ("--set", text)), "--set", f"run.output_dir={tmp_path}",
            "--set", "run.name=cut", "--no-progress", *flags]


def test_sigterm_in_the_first_epoch_stops_like_ctrl_c_and_leaves_nothing(tmp_path, monkeypatch, capsys):
    """SIGTERM (kill, a cluster scheduler) ended the process on the spot: the run folder stayed behind with its
    config, an empty metrics log and a lock but no checkpoint, and nothing was said. Now it is Ctrl-C's path: one
    line, exit 143 (128 + SIGTERM), nothing left on disk, and SIGTERM's own handling back after the command."""
    import os
    import signal

    from warpsense.train import engine

    run_epoch = engine._run_epoch

    def terminated_mid_epoch(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return run_epoch(*args, **kwargs)

    monkeypatch.setattr(engine, "_run_epoch", terminated_mid_epoch)
    assert main(_train_command(tmp_path)) == 143
    error = capsys.readouterr().err
    assert "warpsense train: interrupted before the first epoch ended; nothing to resume" in error
    assert list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


def test_sigterm_while_a_checkpoint_is_written_keeps_the_last_one_and_resumes(tmp_path, monkeypatch, capsys):
    """SIGTERM arriving while epoch 2's checkpoint_last is written: the previous checkpoint stays whole, no .tmp or
    lock is left, the resume command is printed, and the resume trains epochs 2 and 3 with each epoch once in
    metrics.jsonl."""
    import json
    import os
    import signal

    from warpsense.system import checkpoint

    save_file = checkpoint.save_file
    writes = []

    def terminated_while_writing(tensors, filename, metadata=None):
        save_file(tensors, filename, metadata=metadata)  # the temporary is written; the rename has not happened
        if filename.endswith("checkpoint_last.safetensors.tmp"):
            writes.append(filename)
            if len(writes) == 2:
                os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(checkpoint, "save_file", terminated_while_writing)
    assert main(_train_command(tmp_path)) == 143
    run = tmp_path / "cut"
    assert f"continue with: warpsense train --resume-dir {run}" in capsys.readouterr().err
    assert sorted(path.name for path in run.iterdir() if path.name.endswith((".tmp", ".lock"))) == []
    assert json.loads((run / "checkpoint_last.json").read_text())["state"]["epoch"] == 0
    monkeypatch.setattr(checkpoint, "save_file", save_file)
    assert main(["train", "--resume-dir", str(run), "--no-progress"]) == 0
    epochs = [json.loads(line)["epoch"] for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert epochs == [0, 1, 2]
    assert json.loads((run / "checkpoint_last.json").read_text())["state"]["epoch"] == 2


@pytest.mark.parametrize("error", ["CUDA out of memory. Tried to allocate 20.00 GiB.\nOf the allocated memory ...",
                                   "[enforce fail at alloc_cpu.cpp:117] DefaultCPUAllocator: can't allocate memory: "
                                   "you tried to allocate 1000000000000 bytes."])
def test_out_of_memory_is_one_line_error_naming_what_to_lower(capsys, monkeypatch, error):
    """A GPU's or the CPU's allocation failure (eval --latency-size 100000x100000, a batch too large) was a
    traceback; another RuntimeError still is one (a bug, not bad input)."""
    import torch

    from warpsense.cli import COMMANDS

    kind = torch.OutOfMemoryError if "CUDA" in error else RuntimeError

    def fails(args):
        raise kind(error)

    monkeypatch.setattr(COMMANDS["lens"], "run", fails)
    assert main(["lens", "phone_80deg"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"warpsense lens: error: out of memory ({error.splitlines()[0]}): lower the batch size")
    assert len(err.splitlines()) == 1
    monkeypatch.setattr(COMMANDS["lens"], "run", lambda args: (_ for _ in ()).throw(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):
        main(["lens", "phone_80deg"])
