"""Argument pieces several commands share: the config options, counts with a least value, and whether to draw
progress bars."""

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


def parse_gpus(text: str) -> list[str]:
    """``--gpus``: "auto" (every GPU torch sees, none without CUDA), "none", or ids "0,1,3"."""
    if text == "none":
        return []
    if text == "auto":
        import torch

        return [str(i) for i in range(torch.cuda.device_count())] if torch.cuda.is_available() else []
    ids = [part.strip() for part in text.split(",") if part.strip()]
    if not ids or not all(part.isdigit() for part in ids):
        raise ValueError(f"--gpus must be auto, none or GPU ids like 0,1; got {text!r}")
    return ids


def check_local_gpus(ids: list[str]) -> None:
    """GPU ids a local pool will give its workers must name GPUs this process sees: none without CUDA, and below
    torch's device count, which counts within this process's CUDA_VISIBLE_DEVICES (the ids do too, as torch's
    ``cuda:N``; the workers get the entries they name: `warpsense.study.runner.cuda_device`)."""
    if not ids:
        return
    import torch

    from warpsense.study.runner import visible_devices

    if not torch.cuda.is_available():
        raise ValueError(f"--gpus {','.join(ids)}: no CUDA device is visible here; use --gpus none (one process on "
                         "this machine's device) or auto")
    count = torch.cuda.device_count()
    missing = [gpu for gpu in ids if int(gpu) >= count]
    if missing:
        visible = visible_devices()
        seen = (f"this machine has {count}" if visible is None else
                f"CUDA_VISIBLE_DEVICES={','.join(visible)} makes {count} visible, counted from 0 as in PyTorch")
        raise ValueError(f"--gpus {','.join(ids)}: GPU {', '.join(missing)} not found; {seen} (ids 0-{count - 1})")
