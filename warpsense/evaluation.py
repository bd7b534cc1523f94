"""Score a trained checkpoint (`warpsense eval`): re-target it to a dataset and split (its own by default), check
that the dataset labels the classes it predicts, say what the score means (a split it trained on, a fold's held-out
frames, another dataset), then score it, sweep its camera's operating point and time it."""

from __future__ import annotations

import contextlib
from pathlib import Path

from warpsense.files import write_json


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


def retarget(checkpoint: str, config, data: str | None, data_root: str | None, limit: int = 0) -> str:
    """Point a checkpoint's ``config`` (changed in place) at the dataset it is scored on; returns the dataset kind.

    Args:
        checkpoint: the checkpoint's path, for the messages.
        config: the checkpoint's config (`warpsense.system.load_system`).
        data: a dataset kind, or None for the checkpoint's own (said out loud), with its data.root unless
            ``data_root`` is given (a root that is not a folder here asks for --data-root).
        data_root: the dataset folder ("" or None: none, as for generated scenes).
        limit: score only the first ``limit`` images (0: all).
    """
    if data is None:  # the checkpoint's own dataset, said out loud
        data = config.data.dataset
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
    return data


def evaluation_set(config, split: str, trained_on: str):
    """The frames ``split`` names in a `retarget`ed ``config`` (``heldout``: a fold checkpoint's held-out frames),
    with a note where the checkpoint trained on them (a fold's other frames of the split, or the training split
    itself): that score measures fit, not accuracy on new frames."""
    from warpsense.data import HELDOUT_SPLIT, DatasetError, build_dataset, build_fold, fold_name, frame_sequences
    from warpsense.data.datasets import split_parts

    data, fold = config.data, config.data.holdout_sequence
    own = data.dataset == trained_on
    if split == HELDOUT_SPLIT:  # a fold checkpoint's own judge: the frames it never saw nor sat beside
        if not fold_name(data):
            raise ValueError(f"--split {HELDOUT_SPLIT}: the checkpoint was not trained on a fold (its "
                             "data.holdout_sequence and data.holdout_block are empty); name a split, e.g. --split val")
        return build_fold(data, train=False, seed=config.run.seed)
    dataset = build_dataset(data, split, train=False, seed=config.run.seed)
    seen = set()
    if data.holdout_block and own and split in (data.train_split, data.val_split):
        print(f"note: the checkpoint trained on most frames of {split} (its fold held out "
              f"{fold_name(data)}); --split {HELDOUT_SPLIT} scores the frames it did not train on")
    if fold and own:
        with contextlib.suppress(DatasetError):  # frames without sequence names: nothing to say
            seen = set(frame_sequences(dataset)) - {fold}
    if seen and split in (data.train_split, data.val_split):
        print(f"note: the checkpoint trained on the frames of {split} from {', '.join(sorted(seen))} (its fold "
              f"held out {fold} only); --split {HELDOUT_SPLIT} scores the held-out sequence")
    elif not fold and own and split in split_parts(data.train_split):
        print(f"note: the checkpoint trained on {split} (data.train_split = {data.train_split!r}): this "
              "score measures fit to frames it saw, not accuracy on new ones")
    return dataset


def run_eval(checkpoint: str, data: str | None, data_root: str | None, split: str, json_out: str | None = None,
             sweep: bool = False, latency: bool = False, latency_size: tuple[int, int] = (192, 640),
             latency_batch: int = 1, device: str = "auto", batch_size: int = 4, limit: int = 0,
             plot_out: str | None = None, flip: bool = False, progress: bool = True) -> dict:
    """The `warpsense eval` command as a function; returns the JSON payload. ``latency`` alone (without
    ``sweep``) only times the model: no dataset is read and no mIoU computed."""
    from warpsense.bench.timing import latency_lines, model_latency
    from warpsense.system import load_system, resolve_device
    from warpsense.train.evaluate import evaluate

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
    data = retarget(checkpoint, config, data, data_root, limit)
    dataset = evaluation_set(config, split, trained_on)
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
        payload["sweep"] = _sweep(model, dataset, torch_device, batch_size, class_names, amp, progress, plot_out,
                                  f"robustness sweep: {Path(checkpoint).name}, {data} {split}, "
                                  f"{metrics['num_images']} images")
    if latency:
        payload["latency"] = model_latency(model, torch_device, *latency_size, latency_batch)
        print("\n".join(latency_lines(payload["latency"])))
    if json_out:
        write_json(json_out, payload)
    return payload


def _sweep(model, dataset, device, batch_size: int, class_names: list[str], amp: bool, progress: bool,
           plot_out: str | None, title: str) -> list[dict]:
    """The robustness sweeps' rows (`warpsense.train.evaluate.robustness_sweep`), printed as a table and, with
    ``plot_out``, plotted under ``title``."""
    from warpsense.train.evaluate import robustness_sweep

    rows = robustness_sweep(model, dataset, device, batch_size, class_names, amp, progress)
    print(f"{'factor':>14s} {'value':>8s} {'mIoU':>8s}")
    for row in rows:
        print(f"{row['factor']:>14s} {row['value']:>8g} {row['miou']:>8.4f}")
    if plot_out:
        from warpsense.train.plots import plot_sweep

        plot_sweep(rows, plot_out, title)
    return rows
