"""`warpsense eval`: score a checkpoint on a dataset split, with robustness sweeps and latency."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import torch

from warpsense.files import write_json
from warpsense.system import load_system, resolve_device
from warpsense.train.evaluate import evaluate


def robustness_sweep(model, dataset, device, batch_size: int, class_names, amp: bool,
                     progress: bool = True) -> list[dict]:
    """mIoU under extra blur, scaled noise and other bit depths (one factor at a time, the others at the
    checkpoint's operating point), with a progress bar over the settings; the camera is restored afterwards."""
    from tqdm import tqdm

    camera = model.camera
    operating = {"blur_sigma_px": 0.0, **camera.what_if_values()}
    settings = [("blur_sigma_px", sigma) for sigma in (0.0, 0.5, 1.0, 2.0)]
    if "noise_scale" in operating:
        settings += [("noise_scale", scale) for scale in (0.5, 1.0, 2.0, 4.0)]
    if "bits" in operating:
        settings += [("bits", value) for value in (4, 6, 8, 10, 12)]
    rows = []
    bar = tqdm(settings, desc="sweep", disable=not progress)
    for factor, value in bar:
        bar.set_postfix_str(f"{factor}={value}")
        what_if = {} if factor == "blur_sigma_px" else {factor: value}
        with camera.overridden(**what_if):
            metrics = evaluate(model, dataset, device, batch_size, class_names=class_names, amp=amp,
                               blur_sigma=value if factor == "blur_sigma_px" else 0.0)
        rows.append({"factor": factor, "value": value, "miou": metrics["miou"],
                     "operating_point": value == operating[factor]})
    return rows


def measure_latency(model, device, height: int, width: int, batch: int, repeats: int = 50) -> dict:
    """Median latency (ms) of sensor simulation + network and of the network alone; on CUDA also replayed as
    CUDA graphs. The checkpoint's camera is fixed, so it runs cached (`Camera.cached`), as a deployed one would."""
    from warpsense.bench.timing import time_function
    from warpsense.camera.camera import cached_cameras

    images = torch.randint(0, 256, (batch, 3, height, width), dtype=torch.uint8, device=device)
    sensed = model.sense(images)
    result = {"device": str(device), "height": height, "width": width, "batch": batch, "camera_cached": True}
    with torch.no_grad(), cached_cameras(model):
        result["sensor_plus_network_ms"] = time_function(lambda: model(images), device, repeats)["median_ms"]
        result["network_ms"] = time_function(lambda: model.network(sensed), device, repeats)["median_ms"]
        if device.type == "cuda":
            from warpsense.bench.timing import time_cuda_graph

            result["sensor_plus_network_graph_ms"] = time_cuda_graph(lambda: model(images), repeats)["median_ms"]
            result["network_graph_ms"] = time_cuda_graph(lambda: model.network(sensed), repeats)["median_ms"]
    return result


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


def run_eval(checkpoint: str, data: str | None, data_root: str | None, split: str, json_out: str | None = None,
             sweep: bool = False, latency: bool = False, latency_size: tuple[int, int] = (192, 640),
             latency_batch: int = 1, device: str = "auto", batch_size: int = 4, limit: int = 0,
             plot_out: str | None = None, flip: bool = False, progress: bool = True) -> dict:
    """The `warpsense eval` command as a function; returns the JSON payload. ``latency`` alone (without
    ``sweep``) only times the model: no dataset is read and no mIoU computed."""
    from warpsense.data import HELDOUT_SPLIT, DatasetError, build_dataset, build_fold, frame_sequences

    torch_device = resolve_device(device)
    model, config, state = load_system(checkpoint, torch_device)
    if latency and not sweep:
        payload = {"checkpoint": str(checkpoint), "latency": measure_latency(model, torch_device, *latency_size,
                                                                             latency_batch)}
        print("latency (no scoring; run without --latency for mIoU):", json.dumps(payload["latency"]))
        if json_out:
            write_json(json_out, payload)
        return payload
    trained_on = config.data.dataset
    if data is None:  # the checkpoint's own dataset, said out loud
        data = trained_on
        data_root = config.data.root if data_root is None else data_root
        print(f"dataset: {data} (the checkpoint's; --data picks another)"
              + (f", root {data_root}" if data != "scenes" else ""))
    config.data.dataset = data
    config.data.root = data_root or ""
    config.data.max_val_images = limit
    if data == "scenes":
        config.data.scenes_val = limit or config.data.scenes_val
    fold = config.data.holdout_sequence
    if split == HELDOUT_SPLIT:  # a sequence-fold checkpoint's own judge: the frames of the sequence it never saw
        if not fold:
            raise ValueError(f"--split {HELDOUT_SPLIT}: the checkpoint was not trained on a sequence fold "
                             "(its data.holdout_sequence is empty); name a split, e.g. --split val")
        dataset = build_fold(config.data, train=False, seed=config.run.seed)
    else:
        dataset = build_dataset(config.data, split, train=False, seed=config.run.seed)
        seen = set()
        if fold and data == trained_on:
            with contextlib.suppress(DatasetError):  # frames without sequence names: nothing to say
                seen = set(frame_sequences(dataset)) - {fold}
        if seen and split in (config.data.train_split, config.data.val_split):
            print(f"note: the checkpoint trained on the frames of {split} from {', '.join(sorted(seen))} (its fold "
                  f"held out {fold} only); --split {HELDOUT_SPLIT} scores the held-out sequence")
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
        payload["latency"] = measure_latency(model, torch_device, *latency_size, latency_batch)
        print("latency:", json.dumps(payload["latency"]))
    if json_out:
        write_json(json_out, payload)
    return payload

