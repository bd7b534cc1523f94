"""Argument pieces several commands share: the config options, counts with a least value, and whether to draw
progress bars. The GPUs of a local pool (``--gpus``) are `warpsense.study.launch`'s."""

from __future__ import annotations

import argparse
import sys


def add_config_options(parser: argparse.ArgumentParser,
                       default: str = "default: configs/default.toml", example: str = "train.epochs=5") -> None:
    """``--config`` and ``--set``: the config a command builds (`warpsense.config.load_config`); ``default`` says
    what the command does without ``--config``, ``example`` is a ``section.key=value`` the command reads (the
    help's example of --set)."""
    parser.add_argument("--config", metavar="FILE_OR_PRESET",
                        help=f"a TOML file or a preset name (configs/presets/); {default}")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help=f"override one config key (repeatable), e.g. --set {example}")


def count(minimum: int):
    """An argparse ``type`` for an integer >= ``minimum``: a wrong value is a usage error naming the option, before
    any checkpoint or data is loaded."""
    def convert(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    convert.__name__ = "integer"  # argparse names the type in its "invalid ... value" message
    convert.minimum = minimum  # the least valid value, for the bad-input corpus (tests/reliability)
    return convert


def show_progress(args: argparse.Namespace) -> bool:
    """Whether to draw progress bars: not with --no-progress, and only on a terminal (bars redrawn with carriage
    returns fill a log file with kilobytes of partial lines)."""
    return not args.no_progress and sys.stderr.isatty()
