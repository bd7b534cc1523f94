"""`warpsense train`: a new run, or the continuation of one (which run, and with which config:
`warpsense.train.launch`)."""

from __future__ import annotations

import argparse

from warpsense.commands.options import add_config_options, count, show_progress
from warpsense.config import preset_names
from warpsense.train.launch import run_train
from warpsense.train.run_dir import RunDir


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
                             f"the new end; the previous {RunDir.CONFIG} is kept as config.epoch<E>.json; --set "
                             "changes are allowed with it, as with --allow-config-change, and printed)")
    parser.add_argument("--no-progress", action="store_true",
                        help="hide the progress bars (they are drawn only when stderr is a terminal)")
    parser.add_argument("--print-config", action="store_true",
                        help="print the resolved config (after --config and --set) as JSON and exit")


def run(args: argparse.Namespace) -> int:
    """Run the parsed command (`warpsense.train.launch.run_train`); returns the exit code."""
    return run_train(args.config, args.overrides, args.resume, args.resume_dir, args.allow_config_change,
                     extend=args.extend, progress=show_progress(args), print_config=args.print_config)
