"""`warpsense convert`: raw captures (DNG, Bayer raws) to <stem>.safetensors mosaics, a batch at a time."""

from __future__ import annotations

import argparse

from warpsense.commands.options import show_progress
from warpsense.files import check_output_folder


def register(commands: argparse._SubParsersAction, name: str) -> None:
    """Add the command's parser to ``commands`` (the top-level subparsers) under ``name``."""
    parser = commands.add_parser(name, help="convert raw captures (DNG, Bayer raws) to RAW tensors",
                                 description="Convert raw files (files, folders or globs) into <stem>.safetensors "
                                 "mosaics with metadata, through rawpy/LibRaw.")
    parser.add_argument("inputs", nargs="+", help="raw files, folders or glob patterns")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--force", action="store_true",
                        help="convert every input again (by default an output that already converts the same "
                        "source bytes is kept, so a batch run again after an interruption goes on where it stopped)")
    parser.add_argument("--no-progress", action="store_true",
                        help="hide the progress bar (it is drawn only when stderr is a terminal)")


def run(args: argparse.Namespace) -> int:
    """Run the parsed command (`run_convert`); returns the exit code."""
    return run_convert(args.inputs, args.out, progress=show_progress(args), force=args.force)


def run_convert(inputs: list[str], out_dir: str, progress: bool = True, force: bool = False) -> int:
    """Convert every input into ``out_dir``.

    Returns:
        The exit status: 2 when any input failed (each failure reported on stderr, the others converted), as every
        command's errors exit; else 0.
    """
    from warpsense.data.raw import convert_files

    check_output_folder(out_dir, "--out")
    return 2 if convert_files(inputs, out_dir, progress=progress, force=force) else 0
