"""`warpsense eval`: score a checkpoint on a dataset split, with robustness sweeps and latency
(`warpsense.evaluation`)."""

from __future__ import annotations

import argparse

from warpsense.bench import parse_size
from warpsense.choices import DATASETS, DEVICES
from warpsense.commands.options import count, show_progress
from warpsense.evaluation import run_eval
from warpsense.files import check_output_file, check_plot_file


def register(commands: argparse._SubParsersAction, name: str) -> None:
    """Add the command's parser to ``commands`` (the top-level subparsers) under ``name``."""
    parser = commands.add_parser(name, help="evaluate a checkpoint (mIoU, per-class IoU, sweeps, latency)",
                                 description="Evaluate a trained checkpoint on a dataset split.")
    parser.add_argument("--checkpoint", required=True,
                        help="a checkpoint .safetensors written by `warpsense train` (its config and classes are "
                             "inside it; the .json beside it is a readable copy, not needed)")
    parser.add_argument("--data", choices=DATASETS,
                        help="dataset kind (default: the one the checkpoint was trained on)")
    parser.add_argument("--data-root", help="dataset folder (not needed for scenes; default: the checkpoint's "
                        "data.root when --data is left out)")
    parser.add_argument("--split", default="val",
                        help="split name; heldout: a sequence-fold checkpoint's held-out sequence (default: "
                        "%(default)s)")
    parser.add_argument("--json", metavar="OUT",
                        help="write metrics JSON (miou, per_class_iou, pixel_accuracy, num_images)")
    parser.add_argument("--sweep", action="store_true", help="robustness sweeps: extra blur, noise scale, bit depth")
    parser.add_argument("--flip-tta", action="store_true",
                        help="average with the prediction on the mirrored capture (keeps the CFA phase)")
    parser.add_argument("--plot", metavar="OUT.png", help="with --sweep: plot the sweeps")
    parser.add_argument("--latency", action="store_true",
                        help="time sensor simulation + network (the camera cached: Camera.cached) and network alone "
                             "(alone: no dataset, no mIoU; with --sweep: both)")
    parser.add_argument("--latency-size", metavar="HxW", help="with --latency: its input size (default: 192x640)")
    parser.add_argument("--latency-batch", type=count(1), metavar="N",
                        help="with --latency: its batch size (default: 1)")
    parser.add_argument("--batch-size", type=count(1), default=4, metavar="N",
                        help="evaluation batch size (default: %(default)s)")
    parser.add_argument("--limit", type=count(0), default=0, metavar="N",
                        help="evaluate only the first N images (default: %(default)s = all)")
    parser.add_argument("--device", default="auto", choices=DEVICES, help="device (default: %(default)s)")
    parser.add_argument("--no-progress", action="store_true",
                        help="hide the progress bars (they are drawn only when stderr is a terminal)")


def run(args: argparse.Namespace) -> int:
    """Check the options that depend on each other and where the outputs go, then
    `warpsense.evaluation.run_eval`; returns 0."""
    if args.plot and not args.sweep:
        raise ValueError("--plot draws the sweeps: add --sweep")
    for given, option in ((args.latency_size, "--latency-size"), (args.latency_batch, "--latency-batch")):
        if given is not None and not args.latency:
            raise ValueError(f"{option} sets the input of --latency: add --latency")
    check_output_file(args.json, "--json")
    check_plot_file(args.plot, "--plot")
    # 2 a side: the fixed ISP's demosaic pads by reflection, a torch error (traceback) on a 1-pixel side
    height, width = parse_size(args.latency_size or "192x640", "--latency-size", "192x640", minimum=2)
    run_eval(args.checkpoint, args.data, args.data_root, args.split, args.json, args.sweep, args.latency,
             (height, width), args.latency_batch or 1, args.device, args.batch_size, args.limit, args.plot,
             args.flip_tta, progress=show_progress(args))
    return 0
