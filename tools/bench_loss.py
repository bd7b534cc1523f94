"""The recipe's loss and its terms, forward + backward to the logits, at its training shape (batch 16, 11 classes,
352 x 480; the network's bf16 channels-last logits, 5% of the pixels void), each in one CUDA graph: cross-entropy,
OHEM, the softmax, per-pixel cross-entropy with the softmax (torch's two and the fused op), the Lovasz term and the
smoothness term (the fused op and its plain-torch reference), and the whole loss with the fused ops and with torch's
(`warpsense.train.losses.LOSS_OPS`).

    python tools/bench_loss.py [--device cuda] [--batch 16] [--height 352] [--width 480] [--profile FILE] [--json OUT]

Medians of graph-replay ms (`warpsense.bench.timing.time_cuda_graph`); eager wall-clock ms on a CPU.
``--profile FILE``: the fused whole loss's kernels by GPU time (`write_kernel_table`).
"""

from __future__ import annotations

import argparse
import contextlib
import json

import torch
from torch.nn import functional as F

from warpsense.bench.timing import time_cuda_graph, time_function, write_kernel_table
from warpsense.config import load_config
from warpsense.ops.cross_entropy import softmax_cross_entropy
from warpsense.train import losses


def cases(batch: int, height: int, width: int, device: str) -> dict:
    """name -> a function of no arguments: one forward + backward of that loss or term to the logits."""
    generator = torch.Generator(device=device).manual_seed(0)
    logits = (3 * torch.randn(batch, 11, height, width, device=device, generator=generator)).to(torch.bfloat16)
    logits = logits.to(memory_format=torch.channels_last).requires_grad_()
    labels = torch.randint(0, 11, (batch, height, width), device=device, generator=generator)
    labels[torch.rand(labels.shape, device=device, generator=generator) < 0.05] = 255
    guide = torch.rand(batch, 1, height, width, device=device, generator=generator)
    config = load_config("camvid_codesign", []).loss

    def case(loss_of, *torch_ops):
        def run():
            with losses.LOSS_OPS.torch_ops(*torch_ops) if torch_ops else contextlib.nullcontext():
                return torch.autograd.grad(loss_of(), logits)
        return run

    def probabilities():
        return torch.softmax(logits.float(), dim=1)

    return {
        "cross_entropy": case(lambda: F.cross_entropy(logits.float(), labels, ignore_index=255)),
        "ohem": case(lambda: losses.ohem_cross_entropy(logits, labels, config.ohem_fraction)),
        "softmax": case(lambda: probabilities().sum()),
        "softmax_ce_torch": case(lambda: F.cross_entropy(logits.float(), labels, ignore_index=255, reduction="none")
                                 .sum() + probabilities().square().sum()),
        "softmax_ce_fused": case(lambda: sum(part.square().sum() if part.dim() == 4 else part.sum()
                                             for part in softmax_cross_entropy(logits, labels))),
        "lovasz_fused": case(lambda: losses.lovasz_softmax(logits, labels)),
        "lovasz_torch": case(lambda: losses.lovasz_softmax(logits, labels), "lovasz"),
        "smoothness_fused": case(lambda: losses.edge_aware_smoothness(logits, guide)),
        "smoothness_torch": case(lambda: losses.edge_aware_smoothness(logits, guide), "smoothness"),
        "loss_fused": case(lambda: losses.segmentation_loss(logits, labels, guide, config)[0]),
        "loss_torch": case(lambda: losses.segmentation_loss(logits, labels, guide, config)[0],
                           *losses.LOSS_OPS.names),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--height", type=int, default=352)
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--profile", help="write the fused whole loss's kernel table here")
    parser.add_argument("--json", help="write the medians here")
    args = parser.parse_args()
    cuda = args.device == "cuda"
    shape = (args.batch, args.height, args.width) if cuda else (2, 48, 64)
    results = {"device": torch.cuda.get_device_name() if cuda else "cpu", "shape": [shape[0], 11, *shape[1:]]}
    for name, run in cases(*shape, args.device).items():
        timing = time_cuda_graph(run, 50) if cuda else time_function(run, args.device, 5)
        results[name] = timing["median_ms"]
        print(f"{name:>18s} {timing['median_ms']:8.3f} ms [IQR {timing['iqr_ms']:.3f}]", flush=True)
    if args.profile:
        write_kernel_table(cases(*shape, args.device)["loss_fused"], args.device, args.profile)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(results, handle, indent=1)


if __name__ == "__main__":
    main()
