"""Multi-scale test-time augmentation of a checkpoint, explored on the CPU: the class probabilities of the capture
resized by each scale (the CFA phase kept), averaged, against the capture alone.

    python tools/scale_tta.py [--checkpoint checkpoints/camvid_codesign.safetensors] [--data-root ../shared/data/camvid]
        [--split val] [--sets "1;0.75,1,1.25"] [--limit N] [--json OUT]

Each frame is captured once (the eval-mode camera: noise keyed by the frame's index), as `warpsense eval` does; each
scale resizes that capture, not the scene: a mosaic with 2 x 2 tiles is packed into its four sites, each site
plane resized bilinearly, and unpacked, so every pixel keeps its CFA site; an RGB capture (fixed ISP) is resized as
it is (`warpsense.system.cfa_resize`). The views come from `SensingModel.scaled_views`, whose average over a set is
what `warpsense eval --scale-tta` scores; this tool scores several sets from one pass over the scales. Prints each set's mIoU; ``--json`` writes them. ``--limit N`` takes N frames spread over the split.
"""

from __future__ import annotations

import argparse
import json

import torch

from warpsense.data import build_dataset
from warpsense.system import load_system
from warpsense.train.metrics import ConfusionMatrix


@torch.no_grad()
def scale_sets_miou(checkpoint: str, data_root: str, split: str, sets: list[list[float]], limit: int = 0) -> list[dict]:
    """Per scale set: the mIoU of the averaged probabilities (``sets`` of scales; [1.0] is plain evaluation)."""
    model, config, _ = load_system(checkpoint, "cpu")
    model.eval()
    config.data.root = data_root
    config.data.max_val_images = 0
    dataset = build_dataset(config.data, split, train=False, seed=config.run.seed)
    indices = list(range(len(dataset)))
    if limit:
        indices = indices[:: max(1, len(indices) // limit)][:limit]
    classes = model.network.head.out_channels
    matrices = [ConfusionMatrix(classes, "cpu") for _ in sets]
    scales = sorted({scale for scales in sets for scale in scales})
    for index in indices:
        image, label = dataset[index][:2]
        logits, sensed = model(image[None], image_index=torch.tensor([index]))
        views = model.scaled_views(sensed, logits, scales)  # each scale once, shared by every set holding it
        probabilities = {scale: scale_views[0] for scale, scale_views in zip(scales, views)}
        for matrix, scales_of_set in zip(matrices, sets):
            average = sum(probabilities[scale] for scale in scales_of_set) / len(scales_of_set)
            matrix.update(average.argmax(dim=1), label[None])
    return [{"scales": scales_of_set, "miou": matrix.compute()["miou"], "images": len(indices)}
            for scales_of_set, matrix in zip(sets, matrices)]


def parse_sets(text: str) -> list[list[float]]:
    """"1;0.75,1,1.25" -> [[1.0], [0.75, 1.0, 1.25]]; scales must be > 0."""
    sets = [[float(part) for part in group.split(",")] for group in text.split(";")]
    if any(scale <= 0 for scales in sets for scale in scales):
        raise ValueError("scales must be > 0")
    return sets


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default="checkpoints/camvid_codesign.safetensors")
    parser.add_argument("--data-root", default="../shared/data/camvid")
    parser.add_argument("--split", default="val")
    parser.add_argument("--sets", default="1;0.75,1,1.25", help="scale sets, ';'-separated (default: %(default)s)")
    parser.add_argument("--limit", type=int, default=0, help="N frames spread over the split (0: all)")
    parser.add_argument("--json", metavar="OUT")
    args = parser.parse_args(argv)
    try:
        sets = parse_sets(args.sets)
    except ValueError as error:
        parser.error(f"--sets {args.sets!r}: {error}")
    records = scale_sets_miou(args.checkpoint, args.data_root, args.split, sets, args.limit)
    for record in records:
        print(f"scales {','.join(f'{s:g}' for s in record['scales'])}: mIoU {record['miou']:.4f} "
              f"({record['images']} {args.split} frames)")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(records, handle, indent=1)


if __name__ == "__main__":
    main()
