"""`warpsense eval`: score a checkpoint on a dataset split, with robustness sweeps and latency."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from warpsense.bench import parse_size
from warpsense.choices import DATASETS, DEVICES
from warpsense.commands.options import count, show_progress
from warpsense.files import check_output_file, check_plot_file, write_json


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
    """Check the options that depend on each other and where the outputs go, then `run_eval`; returns 0."""
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


def check_label_space(checkpoint, model, state: dict, dataset, data: str) -> list[str]:
    """The class names to score with, once the checkpoint's classes are known to be the dataset's.

    Args:
        checkpoint: the checkpoint's path, for the message.
        model: the loaded model (its network head's channels are the classes it predicts).
        state: the checkpoint's training state (its ``class_names``: those of the dataset it was trained on).
        dataset: the dataset to score on (its ``classes``).
        data: the dataset's kind, for the message.

    Returns:
        The dataset's class names, in label order.

    Raises:
        ValueError: the network predicts another number of classes than the dataset labels (a run trained with
            ``model.num_classes`` set to more than its dataset's classes, or a Cityscapes checkpoint on CamVid), or
            the same number under other names: its scores would be meaningless.
    """
    names = list(dataset.classes)
    predicted = model.network.head.out_channels
    if predicted != len(names):
        raise ValueError(f"{checkpoint}: the network predicts {predicted} classes, {data} labels {len(names)}: "
                         f"evaluate it on a dataset with its {predicted} classes")
    saved = state.get("class_names")
    if saved and list(saved) != names:
        raise ValueError(f"{checkpoint}: trained on the classes {', '.join(saved)}; {data} labels "
                         f"{', '.join(names)}: evaluate it on a dataset with its classes")
    return names


def _class_table(checkpoint: str, classes_file: str, root: str) -> str:
    """The folder dataset's class table as the checkpoint names it (``data.classes_file``, relative to where it
    trained), or else that path or its file name under the dataset folder ``root``: a checkpoint evaluated from
    another folder finds the table kept with its data."""
    path = Path(classes_file)
    candidates = [path] if path.is_absolute() else [path, Path(root) / path]
    candidates.append(Path(root) / path.name)
    found = next((candidate for candidate in candidates if candidate.is_file()), None)
    if found is None:
        raise ValueError(f"{checkpoint}: its data.classes_file {classes_file!r} is not here nor under --data-root "
                         f"{root or '.'}: put the class table in the dataset folder")
    return str(found)


def run_eval(checkpoint: str, data: str | None, data_root: str | None, split: str, json_out: str | None = None,
             sweep: bool = False, latency: bool = False, latency_size: tuple[int, int] = (192, 640),
             latency_batch: int = 1, device: str = "auto", batch_size: int = 4, limit: int = 0,
             plot_out: str | None = None, flip: bool = False, progress: bool = True) -> dict:
    """The `warpsense eval` command as a function; returns the JSON payload. ``latency`` alone (without
    ``sweep``) only times the model: no dataset is read and no mIoU computed."""
    from warpsense.bench.timing import latency_lines, model_latency
    from warpsense.data import HELDOUT_SPLIT, DatasetError, build_dataset, build_fold, fold_name, frame_sequences
    from warpsense.data.datasets import split_parts
    from warpsense.system import load_system, resolve_device
    from warpsense.train.evaluate import evaluate, robustness_sweep

    torch_device = resolve_device(device)
    model, config, state = load_system(checkpoint, torch_device)
    if latency and not sweep:
        payload = {"checkpoint": str(checkpoint), "latency": model_latency(model, torch_device, *latency_size,
                                                                           latency_batch)}
        print("\n".join(latency_lines(payload["latency"])))
        print("(no scoring; run without --latency for mIoU)")
        if json_out:
            write_json(json_out, payload)
        return payload
    trained_on = config.data.dataset
    if data is None:  # the checkpoint's own dataset, said out loud
        data = trained_on
        if data_root is None:
            data_root = config.data.root
            if data != "scenes" and not Path(data_root).is_dir():  # trained where the data lived elsewhere
                raise ValueError(f"{checkpoint}: its data.root {data_root!r} is not a folder here: pass --data-root "
                                 f"DIR (the {data} folder)")
        print(f"dataset: {data} (the checkpoint's; --data picks another)"
              + (f", root {data_root}" if data != "scenes" else ""))
    config.data.dataset = data
    config.data.root = data_root or ""
    if data == "folder" and config.data.classes_file:
        config.data.classes_file = _class_table(checkpoint, config.data.classes_file, config.data.root)
    config.data.max_val_images = limit
    if data == "scenes":
        config.data.scenes_val = limit or config.data.scenes_val
    fold = config.data.holdout_sequence
    if split == HELDOUT_SPLIT:  # a fold checkpoint's own judge: the frames it never saw nor sat beside
        if not fold_name(config.data):
            raise ValueError(f"--split {HELDOUT_SPLIT}: the checkpoint was not trained on a fold (its "
                             "data.holdout_sequence and data.holdout_block are empty); name a split, e.g. --split val")
        dataset = build_fold(config.data, train=False, seed=config.run.seed)
    else:
        dataset = build_dataset(config.data, split, train=False, seed=config.run.seed)
        seen = set()
        if config.data.holdout_block and data == trained_on and split in (config.data.train_split,
                                                                            config.data.val_split):
            print(f"note: the checkpoint trained on most frames of {split} (its fold held out "
                  f"{fold_name(config.data)}); --split {HELDOUT_SPLIT} scores the frames it did not train on")
        if fold and data == trained_on:
            with contextlib.suppress(DatasetError):  # frames without sequence names: nothing to say
                seen = set(frame_sequences(dataset)) - {fold}
        if seen and split in (config.data.train_split, config.data.val_split):
            print(f"note: the checkpoint trained on the frames of {split} from {', '.join(sorted(seen))} (its fold "
                  f"held out {fold} only); --split {HELDOUT_SPLIT} scores the held-out sequence")
        elif not fold and data == trained_on and split in split_parts(config.data.train_split):
            print(f"note: the checkpoint trained on {split} (data.train_split = {config.data.train_split!r}): this "
                  "score measures fit to frames it saw, not accuracy on new ones")
    class_names = check_label_space(checkpoint, model, state, dataset, data)
    if data != trained_on:
        print(f"note: the checkpoint was trained on {trained_on}; scoring it on {data} (the same "
              f"{len(class_names)} classes) is a transfer test, not its own benchmark")
    amp = torch_device.type == "cuda" and config.train.amp
    metrics = evaluate(model, dataset, torch_device, batch_size, class_names=class_names, amp=amp, progress=progress,
                       flip=flip)
    payload = dict(metrics)
    payload.update({"checkpoint": str(checkpoint), "dataset": data, "trained_on": trained_on, "split": split,
                    "flip_tta": flip})
    print(f"mIoU {metrics['miou']:.4f}  pixel accuracy {metrics['pixel_accuracy']:.4f}  images {metrics['num_images']}")
    for name, iou in metrics["per_class_iou"].items():
        print(f"  {name:>14s}  {'-' if iou is None else f'{iou:.4f}'}")
    if sweep:
        rows = robustness_sweep(model, dataset, torch_device, batch_size, class_names, amp, progress)
        payload["sweep"] = rows
        print(f"{'factor':>14s} {'value':>8s} {'mIoU':>8s}")
        for row in rows:
            print(f"{row['factor']:>14s} {row['value']:>8g} {row['miou']:>8.4f}")
        if plot_out:
            from warpsense.train.plots import plot_sweep

            plot_sweep(rows, plot_out, f"robustness sweep: {Path(checkpoint).name}, {data} {split}, "
                                       f"{metrics['num_images']} images")
    if latency:
        payload["latency"] = model_latency(model, torch_device, *latency_size, latency_batch)
        print("\n".join(latency_lines(payload["latency"])))
    if json_out:
        write_json(json_out, payload)
    return payload

