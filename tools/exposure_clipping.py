"""What a higher exposure gain clips: per class, the share of a split's pixels whose noise-free RAW value reaches the
white level, at each gain (the physics behind docs/runs/plans/camvid_exposure.toml).

    python tools/exposure_clipping.py [--preset camvid_codesign] [--data-root ../shared/data/camvid]
        [--split val] [--gains 1,2,3] [--limit N] [--json OUT]

The preset's camera runs with its exposure held at each gain, the optics, noise and quantization off (a pixel
clips when gain x CFA response x radiance >= 1, the white level of the quantizer), on the dataset's frames turned
into radiance as training does. At gain a the shot-noise SNR of an unclipped pixel grows by sqrt(a) (noise variance
shot * R + read^2 at signal R); this says what that costs. Prints one line per gain; ``--json`` writes them.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from warpsense.config import load_config
from warpsense.data import build_dataset
from warpsense.ops.exposure import exposure_logit
from warpsense.system import build_system


def clipped_shares(preset: str, data_root: str, split: str, gains: list[float], limit: int = 0) -> list[dict]:
    """Per gain: the clipped share of all labelled pixels and of each class's, in [0, 1]. Each frame is read once
    and seen by the camera at every gain."""
    configs = [load_config(preset, [f"data.root={data_root}", "optics.enabled=false", "noise.enabled=false",
                                     "quantize.enabled=false", f"exposure.gain_logit={exposure_logit(gain)}",
                                     "train.cuda_graph=false"]) for gain in gains]
    dataset = build_dataset(configs[0].data, split, train=False, seed=0)
    classes = len(dataset.classes)
    models = [build_system(config, classes).eval() for config in configs]
    clipped, total = np.zeros((len(gains), classes)), np.zeros(classes)
    with torch.no_grad():
        for index in range(min(limit or len(dataset), len(dataset))):
            image, label = dataset[index][:2]
            label = label.numpy()
            known = label < classes  # the void label is left out
            total += np.bincount(label[known], minlength=classes)
            radiance = models[0].radiance(image[None])  # the same for every gain: only the exposure differs
            for row, model in enumerate(models):
                raw = model.camera(radiance, torch.tensor([index]))[0, 0].numpy()
                clipped[row] += np.bincount(label[known & (raw >= 1.0)], minlength=classes)
    return [{"gain": gain, "all": float(shares.sum() / total.sum()),
             "classes": {name: float(shares[c] / total[c]) if total[c] else None for c, name in enumerate(dataset.classes)}}
            for gain, shares in zip(gains, clipped)]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="camvid_codesign")
    parser.add_argument("--data-root", default="../shared/data/camvid")
    parser.add_argument("--split", default="val")
    parser.add_argument("--gains", default="1,2,3", help="comma-separated exposure gains (default: %(default)s)")
    parser.add_argument("--limit", type=int, default=0, help="the first N frames only (0: all)")
    parser.add_argument("--json", metavar="OUT")
    args = parser.parse_args(argv)
    try:
        gains = [float(text) for text in args.gains.split(",")]
        for gain in gains:
            exposure_logit(gain)
    except ValueError as error:
        parser.error(f"--gains {args.gains!r}: {error}")
    records = clipped_shares(args.preset, args.data_root, args.split, gains, args.limit)
    for record in records:
        shares = ", ".join(f"{name} {100 * share:.1f}" for name, share in record["classes"].items() if share is not None)
        print(f"gain {record['gain']:g}: {100 * record['all']:.1f}% of labelled pixels clipped; per class %: {shares}")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(records, handle, indent=1)


if __name__ == "__main__":
    main()
