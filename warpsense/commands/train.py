"""`warpsense train`: a new run, or the continuation of one (which run, and with which config)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from warpsense.commands.options import add_config_options, count, show_progress
from warpsense.config import ConfigError, load_config, preset_names, with_overrides
from warpsense.files import check_output_folder
from warpsense.train.run_dir import BEST, LAST, newest_run, resumed_config

LOCATING_KEYS = ("run.output_dir=", "run.name=")  # overrides that only say where the run to resume is


def register(commands: argparse._SubParsersAction, name: str) -> None:
    """Add the command's parser to ``commands`` (the top-level subparsers) under ``name``."""
    parser = commands.add_parser(name, help="train camera + network (default: built-in scenes on the CPU)",
                                 description="Two-phase co-design training. With no arguments it trains on built-in "
                                 "generated street scenes. Multi-GPU: torchrun --nproc_per_node N -m warpsense train "
                                 "...",
                                 epilog=f"presets: {', '.join(preset_names())}. Every key and its default: "
                                 "configs/default.toml, or --print-config.")
    add_config_options(parser)
    parser.add_argument("--resume", action="store_true",
                        help="continue the run <output_dir>/<name> from its last checkpoint")
    parser.add_argument("--resume-dir", metavar="RUN_DIR", help="continue the run in RUN_DIR from its last checkpoint")
    parser.add_argument("--allow-config-change", action="store_true",
                        help="with --resume/--resume-dir: continue with the given --config/--set even where it "
                             "differs from the run's saved config (refused otherwise; --extend implies it); the "
                             "changes are printed")
    parser.add_argument("--extend", type=count(1), metavar="N",
                        help="with --resume/--resume-dir: train N more epochs after the last checkpoint, finished run "
                             "or not (train.epochs becomes the epochs trained + N, any time budget is dropped; the "
                             "cosine learning rate is laid over the new total, so it rises again and decays to 0 at "
                             "the new end; the previous config.json is kept as config.epoch<E>.json; --set changes "
                             "are allowed with it, as with --allow-config-change, and printed)")
    parser.add_argument("--no-progress", action="store_true",
                        help="hide the progress bars (they are drawn only when stderr is a terminal)")
    parser.add_argument("--print-config", action="store_true",
                        help="print the resolved config (after --config and --set) as JSON and exit")


def run(args: argparse.Namespace) -> int:
    """Run the parsed command (`run_train`); returns the exit code."""
    return run_train(args.config, args.overrides, args.resume, args.resume_dir, args.allow_config_change,
                     extend=args.extend, progress=show_progress(args), print_config=args.print_config)


def check_device_keys(config, source: str = "") -> None:
    """The keys that need the run's device to be a CUDA GPU, checked before the run folder is made, the data read or
    the model built (train.cuda_graph failed only when the training step was set up, after the run directory was
    printed and the model built). ``source`` prefixes the message (a continued run's config.json)."""
    from warpsense.system import resolve_device

    if config.train.cuda_graph:
        device = resolve_device(config.run.device)  # cuda without CUDA is its own one-line error
        if device.type != "cuda":
            raise ConfigError(f"{source}train.cuda_graph = true needs a CUDA device; run.device = "
                              f"{config.run.device!r} is {device} here: add --set train.cuda_graph=false (the camvid "
                              "presets are GPU recipes)")


def trained_epochs(run_dir: Path) -> int:
    """How many epochs the run's last checkpoint holds."""
    from warpsense.system.checkpoint import read_checkpoint, resume_state

    checkpoint = Path(run_dir) / LAST
    tensors, meta = read_checkpoint(checkpoint)
    return resume_state(checkpoint, tensors, meta)["epoch"] + 1


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
    if not (resume or resume_dir):
        config, run_dir = load_config(config_file, overrides), False
        check_output_folder(config.run.output_dir, "run.output_dir")
    else:
        locating = [text for text in overrides if text.startswith(LOCATING_KEYS)]
        changes = [text for text in overrides if text not in locating]
        if resume_dir:
            run_dir = Path(resume_dir)
        else:
            located = load_config(config_file, locating)
            run_dir = newest_run(located.run.output_dir, located.run.name)
        extended = []
        if extend is not None:  # validated with the user's changes, as one config: a warm-up may need the new epochs
            trained = trained_epochs(run_dir)
            extended = [f"train.epochs={trained + extend}", "train.time_budget_minutes=0.0"]
            allow_config_change = True
        try:
            if config_file is not None:
                config = load_config(config_file, [*overrides, *extended])
            else:
                config = with_overrides(resumed_config(run_dir, None), [*changes, *extended]) \
                    if changes or extended else None
        except ConfigError as error:
            if not extended or "train.epochs" not in str(error):
                raise
            # say where train.epochs came from: the user did not set it
            raise ConfigError(f"{error} (--extend {extend}: train.epochs = {trained} trained + {extend})") from None
    if config is not None:
        check_device_keys(config)
    elif (Path(run_dir) / LAST).is_file():  # continued with its own config (train() says where none is to resume)
        check_device_keys(resumed_config(run_dir, None), f"{Path(run_dir) / 'config.json'}: ")
    # train() checks the rest (a change of task, the stages' checks, the files the run needs) before it writes
    try:
        train(config, resume=run_dir, progress=progress, allow_config_change=allow_config_change)
    except TrainingInterrupted as interrupted:
        if progress:  # the epoch's bar is left mid-line: start the message on a line of its own
            print(file=sys.stderr)
        if not (interrupted.run_dir / LAST).is_file() and (interrupted.run_dir / BEST).is_file():
            print(f"warpsense train: interrupted before the run's first resume point (train.checkpoint_every); "
                  f"nothing to resume, but its best checkpoint so far is kept: {interrupted.run_dir / BEST}; start "
                  "the run again to train it (in a new folder)", file=sys.stderr)
            return 130
        if not (interrupted.run_dir / LAST).is_file():
            print(f"warpsense train: interrupted before the first epoch ended; nothing to resume in "
                  f"{interrupted.run_dir}: start the run again", file=sys.stderr)
            return 130
        print(f"warpsense train: interrupted; continue with: warpsense train --resume-dir {interrupted.run_dir}",
              file=sys.stderr)
        return 130
    return 0
