"""`warpsense simulate`: sRGB (or linear) images through a configured or checkpointed camera to RAW files."""

from __future__ import annotations

import argparse

from warpsense.choices import DEVICES
from warpsense.commands.options import add_config_options, count
from warpsense.files import check_output_folder


def register(commands: argparse._SubParsersAction, name: str) -> None:
    """Add the command's parser to ``commands`` (the top-level subparsers) under ``name``."""
    parser = commands.add_parser(
        name, help="your own images through a camera: RAW (.safetensors, DNG) and a preview",
        description="Take sRGB images (PNG/JPEG; linear TIFFs with --linear) through a configured or checkpointed "
        "camera in eval mode (fixed noise seed) and write per image <stem>.safetensors (the RAW mosaic, which "
        "`warpsense predict` reads), <stem>.dng (where the CFA is a 2x2 Bayer layout) and <stem>.preview.png. A bad "
        "file is reported and the others go on (exit 2 at the end).")
    parser.add_argument("images", nargs="+", help="image files")
    add_config_options(parser, default="the camera: required unless --checkpoint", example="quantize.bits=8")
    parser.add_argument("--checkpoint", metavar="CKPT", help="use a trained checkpoint's camera instead of --config")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--linear", action="store_true",
                        help="the images hold linear radiance (16-bit or float TIFF) instead of sRGB")
    parser.add_argument("--seed", type=count(0), default=0, metavar="N",
                        help="noise seed offset (with the camera's eval seed and the file name; default: "
                        "%(default)s)")
    parser.add_argument("--device", choices=DEVICES, default=None,
                        help="where the camera runs; cuda without a CUDA GPU is an error (default: the config's "
                        "run.device, auto with --checkpoint)")


def run(args: argparse.Namespace) -> int:
    """Check that the camera is given once, then `run_simulate`; returns the exit code."""
    if args.checkpoint and (args.config or args.overrides):
        raise ValueError("--checkpoint brings its own camera: leave out --config and --set")
    if not args.checkpoint and not args.config:
        raise ValueError("give the camera: --config FILE_OR_PRESET (with --set) or --checkpoint CKPT")
    return run_simulate(args.images, args.out, args.config, args.overrides, args.checkpoint, args.linear, args.seed,
                        args.device)


def run_simulate(inputs: list[str], out_dir: str, config: str | None = None, overrides: list[str] = (),
                 checkpoint: str | None = None, linear: bool = False, seed: int = 0,
                 device: str | None = None) -> int:
    """Simulate every input into ``out_dir`` (`warpsense.simulate`) with the camera on ``device`` (None: the
    config's run.device, auto for a checkpoint; `warpsense.simulate.load_camera`).

    Returns:
        The exit status: 2 when any input failed (each reported on stderr, the others written), else 0.
    """
    from warpsense.simulate import load_camera, simulate_files

    check_output_folder(out_dir, "--out")
    camera = load_camera(config, overrides, checkpoint, device)
    return 2 if simulate_files(inputs, out_dir, camera, linear=linear, seed=seed) else 0
