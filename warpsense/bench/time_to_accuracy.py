"""`warpsense bench --suite time-to-accuracy --camvid DIR`: wall time to reach val mIoU levels, the CamVid recipe
against the plain-torch baseline of the train suite, in one run on one device.

- recipe: `warpsense train --config camvid_codesign` as shipped (`warpsense.train.engine.train`), validated every
  ``eval_every`` epochs; its times are the run's own ``wall_s`` (setup, training and evaluation included).
- baseline: the train suite's plain-torch camera (`BaselineCamera`: a 7x7 Gaussian via conv2d, eager sensor ops)
  with the same network, loss (its smoothness term in plain torch), optimizer, cosine schedule, epochs, training
  data on the device and validation, trained by a plain eager loop (no compile, no CUDA graph), as a user's script
  would be.

Records: one per method with its curve (epoch, wall_s, val mIoU), its final val, the time to each level in
``LEVELS`` (None if never reached), the time to the baseline's final val, where the start went (``setup_s``, until
the first step; ``first_epoch_s``, the first epoch with any compile or graph capture; for the recipe ``capture_s``,
its CUDA graph captures in both phases) and ``network_parameters`` (equal for both: the same network). Before any
method is timed, `process_warmup` pays a new process's first-use costs once for both (``process_warmup_s`` in every
record): without it the method timed first pays them for the other. With
several ``--seeds`` every seed trains both methods, and one summary record per method gives the final val, the end
time and the time to the baseline's final val as means with 95% t intervals, the recipe's also paired by seed against
the baseline. ``--quick`` trains 2 epochs on 8 images at a small crop (CI time on a CPU).
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import torch

from warpsense.bench.train_suite import BaselineCamera, method_ops
from warpsense.camera.camera import set_finite_check
from warpsense.config import load_config
from warpsense.data import build_dataset
from warpsense.data.on_device import DecodedDataset
from warpsense.models import count_parameters, network_from_config
from warpsense.system import SensingModel
from warpsense.system.build import build_system
from warpsense.train.distributed import DistributedContext
from warpsense.train.engine import build_train_batches, eval_batch_size, every, train
from warpsense.train.evaluate import evaluate
from warpsense.train.losses import segmentation_loss
from warpsense.train.run_dir import RunDir
from warpsense.train.step import TrainingStep

LEVELS = (0.5, 0.6, 0.65, 0.7)
"""Val mIoU levels the suite times (the CamVid recipe ends near 0.71 at the night point, the
plain-torch baseline near 0.66)."""

QUICK = ["data.max_train_images=8", "data.max_val_images=4", "data.batch_size=2", "data.crop_height=64",
         "data.crop_width=96", "train.epochs=2", "train.warmup_epochs=1", "train.eval_every=1", "model.width=8"]


def suite_config(camvid_root: str, device: str, quick: bool, output_dir: str, eval_every: int = 5, seed: int = 0):
    """The camvid_codesign preset on ``camvid_root`` with the training data on the device, validated every
    ``eval_every`` epochs, with ``run.seed`` = ``seed`` (``QUICK``: a tiny run); on a CPU without compile or CUDA
    graph."""
    overrides = [f"data.root={camvid_root}", f"run.output_dir={output_dir}", "train.plots=false",
                 f"train.eval_every={eval_every}", f"run.device={device}", "data.on_device=always", f"run.seed={seed}"]
    if device != "cuda":
        overrides += ["train.compile=off", "train.cuda_graph=false"]
    return load_config("camvid_codesign", overrides + (QUICK if quick else []))


def time_to(curve: list[dict], level: float) -> float | None:
    """Wall seconds at the first validation reaching ``level`` (None: never)."""
    return next((point["wall_s"] for point in curve if point["val_miou"] >= level), None)


def baseline_system(config, num_classes: int) -> SensingModel:
    """The baseline's system: the train suite's plain-torch camera (`BaselineCamera`) and the config's network on its
    one-channel mosaic."""
    return SensingModel(BaselineCamera(), network_from_config(config.model, 1, num_classes, tile=2))


def baseline_curve(config, device: torch.device) -> tuple[list[dict], dict]:
    """Train the plain-torch baseline under ``config``'s data, network, loss and schedule; its validation curve and
    start times."""
    started = time.perf_counter()
    torch.manual_seed(config.run.seed)
    train_set = build_dataset(config.data, config.data.train_split, train=True, seed=config.run.seed)
    # decoded onto the device once, as the recipe's engine does with its training data there
    val_set = DecodedDataset(build_dataset(config.data, config.data.val_split, train=False, seed=config.run.seed),
                             device)
    context = DistributedContext(device=device)
    batches = build_train_batches(config, train_set, context, progress=False)
    steps = min(len(batches), config.train.max_steps_per_epoch or len(batches))
    model = baseline_system(config, len(train_set.classes)).to(device).train()
    set_finite_check(model, False)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.train.lr, weight_decay=config.train.weight_decay)
    amp = config.train.amp and device.type == "cuda"
    total = config.train.epochs * steps
    step = TrainingStep(config.loss, optimizer, [], total, amp)
    curve, index = [], 0
    start = {"setup_s": time.perf_counter() - started, "network_parameters": count_parameters(model.network)}
    with method_ops("torch_baseline"):  # a plain PyTorch script: the network and loss through torch's own ops
        for epoch in range(config.train.epochs):
            batches.set_epoch(epoch)
            model.train()
            epoch_started = time.perf_counter()
            for _, (images, labels) in zip(range(steps), batches):
                step(model, images.to(device), labels.to(device), index, joint=True)
                index += 1
            if epoch == 0:
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                start["first_epoch_s"] = time.perf_counter() - epoch_started
            if every(epoch, config.train.eval_every, config.train.epochs):
                metrics = evaluate(model, val_set, device, eval_batch_size(config), amp=amp)
                curve.append({"epoch": epoch, "wall_s": time.perf_counter() - started, "val_miou": metrics["miou"]})
    return curve, start


def process_warmup(config, device: torch.device) -> float:
    """One untimed forward + backward of the recipe's system and of the baseline's, at the training batch and crop
    with bf16 autocast and the loss as they train, in this process: what the first method timed would otherwise pay
    for both (Warp's modules loaded from its kernel cache or built, torch's custom-op machinery imported on first
    call, cuDNN's kernels loaded): without it the method timed first pays them in its first epoch, several times the
    other's. Its wall seconds; nothing trains (the parameters' gradients are dropped)."""
    started = time.perf_counter()
    classes = len(build_dataset(config.data, config.data.val_split, train=False, seed=config.run.seed).classes)
    shape = (config.data.batch_size, 3, config.data.crop_height, config.data.crop_width)
    images = torch.randint(0, 256, shape, dtype=torch.uint8, device=device)
    labels = torch.randint(0, classes, (shape[0], *shape[2:]), device=device)
    amp = config.train.amp and device.type == "cuda"
    for method, model in (("warpsense", build_system(config, classes)),
                          ("torch_baseline", baseline_system(config, classes))):
        model = model.to(device).train()
        with method_ops(method):
            logits, sensed = model(images, amp)
            loss, _ = segmentation_loss(logits, labels, sensed, config.loss)
            loss.backward()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - started


def recipe_curve(config) -> tuple[list[dict], dict]:
    """Train the recipe with `warpsense train`'s engine; its validation curve and start times from the run's
    metrics."""
    run, model = train(config, progress=False, return_model=True)
    records = RunDir(run).read_metrics()
    start = {"setup_s": records[0]["setup_s"], "first_epoch_s": records[0]["epoch_time_s"],
             "capture_s": sum(r.get("capture_s", 0.0) for r in records),  # CUDA graphs, both phases
             "network_parameters": count_parameters(model.network)}
    return [{"epoch": r["epoch"], "wall_s": r["wall_s"], "val_miou": r["val_miou"]} for r in records
            if "val_miou" in r], start


def run_time_to_accuracy_suite(device: str, quick: bool, camvid_root: str | None, metadata: dict,
                               seeds: tuple[int, ...] = (0,)) -> list[dict]:
    """Both methods' records for each seed (the recipe, then the baseline, with ``run.seed`` = seed; printed as a
    table as they finish), and with several seeds one summary record per method (`summarise`)."""
    if not camvid_root:
        raise ValueError("--suite time-to-accuracy needs --camvid ROOT (the CamVid folder with train.txt and val.txt)")
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds must name distinct seeds, got {list(seeds)}")
    records = []
    for seed in seeds:
        with tempfile.TemporaryDirectory(prefix="warpsense-tta-") as output_dir:
            config = suite_config(camvid_root, device, quick, output_dir, seed=seed)
            warmup_s = process_warmup(config, torch.device(device))
            curves, starts = {}, {}
            for method, trainer in (("warpsense recipe", recipe_curve),
                                    ("torch_baseline", lambda c: baseline_curve(c, torch.device(device)))):
                curves[method], starts[method] = trainer(config)
                starts[method]["process_warmup_s"] = warmup_s
                # each curve as soon as it exists: a run stopped during the second method keeps the first
                record = {**starts[method], "curve": curves[method]}
                print(f"time-to-accuracy {method} seed {seed}: " + json.dumps(record), flush=True)
        records += _seed_records(curves, starts, config, device, metadata, seed)
    if len(seeds) > 1:
        records += summarise(records)
    return records


def _seed_records(curves: dict, starts: dict, config, device: str, metadata: dict, seed: int) -> list[dict]:
    """One record per method of one seed, each timed to that seed's baseline final val; the table rows."""
    baseline_final = curves["torch_baseline"][-1]["val_miou"]
    records = []
    print(f"time-to-accuracy {'method':>17s} {'seed':>4s} {'final val':>9s} {'end s':>8s} "
          + " ".join(f"{'to ' + format(level, '.2f'):>8s}" for level in LEVELS)
          + f" {'to baseline':>11s} {'setup s':>8s} {'epoch 1 s':>9s} {'warm-up s':>9s}", flush=True)
    for method, curve in curves.items():
        record = {"suite": "time-to-accuracy", "method": method, "seed": seed, "device": device,
                  "device_name": metadata.get("device_name"), "epochs": config.train.epochs,
                  "images": [config.data.batch_size, 3, config.data.crop_height, config.data.crop_width],
                  "curve": curve, "final_val_miou": curve[-1]["val_miou"], "wall_s": curve[-1]["wall_s"],
                  **starts[method],
                  "time_to": {f"{level:.2f}": time_to(curve, level) for level in LEVELS},
                  "time_to_baseline_final": time_to(curve, baseline_final)}
        records.append(record)
        cells = " ".join(f"{value:8.1f}" if value is not None else f"{'-':>8s}" for value in record["time_to"].values())
        reached = record["time_to_baseline_final"]
        print(f"time-to-accuracy {method:>17s} {seed:4d} {record['final_val_miou']:9.4f} {record['wall_s']:8.1f} "
              f"{cells} {format(reached, '11.1f') if reached is not None else format('-', '>11s')} "
              f"{record['setup_s']:8.1f} {record['first_epoch_s']:9.1f} {record['process_warmup_s']:9.1f}", flush=True)
    return records


SUMMARISED = ("final_val_miou", "wall_s", "time_to_baseline_final")
"""The per-seed figures a summary gives as a mean with its 95% t interval."""


def summarise(records: list[dict]) -> list[dict]:
    """Per method over the seeds: the mean and 95% t interval of each of ``SUMMARISED`` (None where a seed never
    reached its baseline's final val, with ``reached`` counting the seeds that did), and for the recipe the
    seed-paired difference to the baseline (recipe minus baseline; `warpsense.study.statistics.paired_difference`).
    Printed as a table."""
    from warpsense.study.statistics import paired_difference, t_interval

    by_method: dict[str, dict[int, dict]] = {}
    for record in records:
        by_method.setdefault(record["method"], {})[record["seed"]] = record
    baseline = by_method["torch_baseline"]
    summaries = []
    print(f"time-to-accuracy summary over seeds {sorted(baseline)} (mean [95% t]; difference: recipe - baseline, "
          "paired by seed)", flush=True)
    for method, runs in by_method.items():
        summary = {"suite": "time-to-accuracy", "method": method, "summary": True, "seeds": sorted(runs)}
        for key in SUMMARISED:
            values = {seed: run[key] for seed, run in runs.items()}
            reached = {seed: value for seed, value in values.items() if value is not None}
            summary[key] = t_interval(list(reached.values())) if len(reached) == len(values) else None
            summary[f"{key}_reached"] = len(reached)
            if method != "torch_baseline" and summary[key] is not None:
                partner = {seed: baseline[seed][key] for seed in reached if baseline[seed][key] is not None}
                summary[f"{key}_difference"] = paired_difference(reached, partner) if partner else None
        summaries.append(summary)
        differences = {key: summary.get(key + "_difference") for key in SUMMARISED}
        print(f"time-to-accuracy {method:>17s} " + "  ".join(
            f"{key} {_interval_text(summary[key])}"
            + (f" (difference {_interval_text(differences[key])})" if differences[key] else "")
            for key in SUMMARISED), flush=True)
    return summaries


def _interval_text(interval: dict | None) -> str:
    if interval is None:
        return "- (not every seed reached it)"
    if interval["low"] is None:
        return f"{interval['mean']:.4g}"
    return f"{interval['mean']:.4g} [{interval['low']:.4g}, {interval['high']:.4g}]"


def plot_time_to_accuracy(records: list[dict], path: str | Path) -> None:
    """Val mIoU against wall time, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6, 4))
    runs = [record for record in records if not record.get("summary")]
    several = len({record.get("seed", 0) for record in runs}) > 1
    colours = {}
    for record in runs:
        curve = record["curve"]
        colour = colours.setdefault(record["method"], f"C{len(colours)}")
        label = f"{record['method']}, seed {record.get('seed', 0)}" if several else record["method"]
        axis.plot([p["wall_s"] for p in curve], [p["val_miou"] for p in curve], marker="o", color=colour, label=label,
                  alpha=0.8 if several else 1.0)
    axis.set_xlabel("wall time (s)"), axis.set_ylabel("val mIoU")
    axis.set_title(f"time to accuracy, {runs[0]['epochs']} epochs, {runs[0].get('device_name') or runs[0]['device']}",
                   fontsize=10)
    axis.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
