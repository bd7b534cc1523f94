"""Start or continue a training run as `warpsense train` asks: which run (a new one, the newest of a config, a run
directory), with which config (the given one, the run's own, the run's with changes or more epochs), checked before
anything is written, and what an interrupted run says about going on."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from warpsense.config import ConfigError, load_config, with_overrides
from warpsense.files import check_output_folder
from warpsense.train.run_dir import RunDir, newest_run, resumed_config

LOCATING_KEYS = ("run.output_dir=", "run.name=")
"""Overrides that only say where the run to resume is."""


def check_device_keys(config, source: str = "") -> None:
    """The keys that need the run's device to be a CUDA GPU, checked before the run folder is made, the data read or
    the model built, so that a run its machine cannot train leaves nothing behind and costs no set-up. ``source``
    prefixes the message (a continued run's `RunDir.config`)."""
    from warpsense.system import resolve_device

    if config.train.cuda_graph:
        device = resolve_device(config.run.device)  # cuda without CUDA is its own one-line error
        if device.type != "cuda":
            raise ConfigError(f"{source}train.cuda_graph = true needs a CUDA device; run.device = "
                              f"{config.run.device!r} is {device} here: add --set train.cuda_graph=false (the camvid "
                              "presets are GPU recipes)")


def trained_epochs(run_dir: Path) -> int:
    """How many epochs the run's last checkpoint holds (`RunDir.trained_epochs`)."""
    return RunDir(run_dir).trained_epochs()


def run_train(config_file: str | None, overrides: list[str], resume: bool = False, resume_dir: str | None = None,
              allow_config_change: bool = False, progress: bool = True, print_config: bool = False,
              extend: int | None = None) -> int:
    """Train; returns the exit code (130 after Ctrl-C, with the command that continues the run on stderr).

    Args:
        config_file: a preset name or TOML file (None: the defaults).
        overrides: ``section.key=value`` strings.
        resume: continue the newest run <output_dir>/<name>[-N] of the config.
        resume_dir: continue this run directory.
        allow_config_change: when continuing, use ``config_file`` / ``overrides`` even where they differ from the
            run's saved config (refused otherwise). Without them a run continues with its own config.
        progress: show progress bars.
        extend: with ``resume`` / ``resume_dir``: train this many epochs more than the last checkpoint holds
            (finished run or not): train.epochs becomes the epochs trained + ``extend`` and the time budget is
            dropped.
        print_config: print the resolved config (JSON, as each run saves it) and return without training.
    """
    from warpsense.train.engine import TrainingInterrupted, train

    if print_config:
        print(json.dumps(load_config(config_file, overrides).to_dict(), indent=2))
        return 0
    _check_options(resume, resume_dir, allow_config_change, extend)
    if not (resume or resume_dir):
        config, run_dir = load_config(config_file, overrides), False
        check_output_folder(config.run.output_dir, "run.output_dir")
    else:
        if resume_dir:
            run_dir = Path(resume_dir)
        else:
            located = load_config(config_file, [text for text in overrides if text.startswith(LOCATING_KEYS)])
            run_dir = newest_run(located.run.output_dir, located.run.name)
        config = _continued_config(RunDir(run_dir), config_file, overrides, extend)
        allow_config_change = allow_config_change or extend is not None
    if config is not None:
        check_device_keys(config)
    elif RunDir(run_dir).resumable():  # continued with its own config (train() says where none is to resume)
        check_device_keys(resumed_config(run_dir, None), f"{RunDir(run_dir).config}: ")
    # train() checks the rest (a change of task, the stages' checks, the files the run needs) before it writes
    try:
        train(config, resume=run_dir, progress=progress, allow_config_change=allow_config_change)
    except TrainingInterrupted as interrupted:
        if progress:  # the epoch's bar is left mid-line: start the message on a line of its own
            print(file=sys.stderr)
        print(f"warpsense train: {interrupted_message(RunDir(interrupted.run_dir))}", file=sys.stderr)
        return 130
    return 0


def _check_options(resume: bool, resume_dir: str | None, allow_config_change: bool, extend: int | None) -> None:
    """The options that go together: one way to name the run to continue, and the continuation's own options."""
    if resume and resume_dir:
        raise ValueError(f"--resume continues the newest run of the config, --resume-dir {resume_dir} a run of your "
                         "choice: give one of them")
    if extend is not None and not (resume or resume_dir):
        raise ValueError("--extend continues a run: give --resume or --resume-dir")
    if allow_config_change and not (resume or resume_dir):
        raise ValueError("--allow-config-change lets a continued run take changed --config/--set values: give "
                         "--resume or --resume-dir")
    if extend is not None and extend < 1:
        raise ValueError(f"--extend must be a number of epochs >= 1, got {extend}")


def _continued_config(run: RunDir, config_file: str | None, overrides: list[str], extend: int | None):
    """The config a continuation of ``run`` asks for: the given file with ``overrides``, the run's own with the
    overrides that change it, or None (the run's own, unchanged); ``extend`` adds train.epochs = the epochs trained
    + ``extend`` with no time budget, validated with the user's changes as one config."""
    changes = [text for text in overrides if not text.startswith(LOCATING_KEYS)]
    extended = []
    if extend is not None:  # validated with the user's changes, as one config: a warm-up may need the new epochs
        trained = run.trained_epochs()
        extended = [f"train.epochs={trained + extend}", "train.time_budget_minutes=0.0"]
    try:
        if config_file is not None:
            return load_config(config_file, [*overrides, *extended])
        return with_overrides(resumed_config(run.path, None), [*changes, *extended]) if changes or extended else None
    except ConfigError as error:
        if not extended or "train.epochs" not in str(error):
            raise
        # say where train.epochs came from: the user did not set it
        raise ConfigError(f"{error} (--extend {extend}: train.epochs = {trained} trained + {extend})") from None


def interrupted_message(run: RunDir) -> str:
    """What an interrupted run says about going on: how to continue it, or why there is nothing to continue."""
    if not run.resumable() and run.best.is_file():
        return (f"interrupted before the run's first resume point (train.checkpoint_every); nothing to resume, but "
                f"its best checkpoint so far is kept: {run.best}; start the run again to train it (in a new folder)")
    if not run.resumable():
        return f"interrupted before the first epoch ended; nothing to resume in {run}: start the run again"
    return f"interrupted; continue with: warpsense train --resume-dir {run}"
