"""`warpsense predict`: segment a real raw capture with a checkpoint trained with a fixed Bayer CFA
(`warpsense.predict`)."""

from __future__ import annotations

import argparse

from warpsense.choices import DEVICES
from warpsense.files import check_output_file
from warpsense.predict import predict_raw


def register(commands: argparse._SubParsersAction, name: str) -> None:
    """Add the command's parser to ``commands`` (the top-level subparsers) under ``name``."""
    parser = commands.add_parser(name, help="segment a real raw capture with a fixed-Bayer checkpoint",
                                 description="Run a checkpoint trained with a fixed Bayer CFA on a DNG and write a "
                                 "colour-coded segmentation PNG.")
    parser.add_argument("checkpoint", help="checkpoint .safetensors")
    parser.add_argument("input", help="raw file (DNG, or another LibRaw raw) or a `warpsense convert` .safetensors")
    parser.add_argument("--out", required=True,
                        help="output image, as large as the capture; its type follows the suffix (.png, .jpg, ...)")
    parser.add_argument("--overlay", action="store_true", help="blend the class colours over the capture")
    parser.add_argument("--no-legend", action="store_true", help="leave out the strip naming the class colours")
    parser.add_argument("--device", default="auto", choices=DEVICES, help="device (default: %(default)s)")


def run(args: argparse.Namespace) -> int:
    """Check where the image goes, then `warpsense.predict.predict_raw`; returns 0."""
    check_output_file(args.out, "--out")
    predict_raw(args.checkpoint, args.input, args.out, device=args.device, overlay=args.overlay,
                legend=not args.no_legend)
    return 0
