"""Validation's cost and result by evaluation batch size (`train.eval_batch_size`): train the recipe briefly with
the engine, then evaluate the val split at each batch size, timed (the median of ``--repeats``), with each size's
mIoU and whether its confusion matrix equals the first size's.

    python tools/bench_eval.py --camvid DIR [--config camvid_codesign] [--epochs 10] [--batches 8,16,32]
                               [--repeats 3] [--set KEY=VALUE ...] [--json OUT]

The metrics should not depend on the batch (eval-mode camera, noise seeded by each image's index); on a GPU the
convolutions' algorithms may differ by batch, so bf16 rounding can move a few pixels' argmax.
"""

from __future__ import annotations

import argparse
import json
import tempfile

import torch

from warpsense.bench.timing import time_function
from warpsense.config import load_config
from warpsense.data import build_dataset
from warpsense.data.on_device import DecodedDataset
from warpsense.train.engine import train
from warpsense.train.evaluate import evaluate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--camvid", required=True, help="the CamVid root (data.root)")
    parser.add_argument("--config", default="camvid_codesign")
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--batches", default="8,16,32")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--set", action="append", default=[], help="a config override KEY=VALUE (repeatable)")
    parser.add_argument("--json")
    args = parser.parse_args()
    batches = [int(b) for b in args.batches.split(",")]
    with tempfile.TemporaryDirectory() as out:
        overrides = [f"data.root={args.camvid}", f"train.epochs={args.epochs}",
                     f"train.warmup_epochs={max(1, args.epochs // 3)}", f"train.eval_every={args.epochs}",
                     "train.plots=false", f"run.output_dir={out}", *args.set]
        config = load_config(args.config, overrides)
        _, model = train(config, progress=False, return_model=True)
    device = next(model.parameters()).device
    amp = config.train.amp and device.type == "cuda"
    val = DecodedDataset(build_dataset(config.data, config.data.val_split, train=False, seed=config.run.seed),
                         device)
    results = {"device": torch.cuda.get_device_name() if device.type == "cuda" else "cpu", "images": len(val),
               "epochs": args.epochs, "batches": {}}
    first = None
    for batch in batches:
        runs = []

        def run(batch=batch, runs=runs):
            runs.append(evaluate(model, val, device, batch, amp=amp, per_image=True))

        timing = time_function(run, device, args.repeats, warmup=0)
        metrics = runs[-1]
        counts = metrics["image_counts"]
        first = counts if first is None else first
        row = {"median_s": timing["median_ms"] / 1e3, "miou": metrics["miou"],
               "same_counts_as_first": bool(torch.equal(counts, first)),
               "count_difference_from_first": int((counts - first).abs().sum())}
        results["batches"][batch] = row
        print(f"eval batch {batch:3d}: {row['median_s']:.3f} s  mIoU {row['miou']:.6f}  same counts as batch "
              f"{batches[0]}: {row['same_counts_as_first']}", flush=True)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(results, handle, indent=1)


if __name__ == "__main__":
    main()
