"""The decoder join (`warpsense.ops.upsample_concat`) against torch's resize + concatenation, DSUNet's four joins at
the recipe's training shape (width 24, batch 16, 352 x 480), channels-last, forward and forward + backward.

    python tools/bench_upsample.py [--device cuda] [--quick]

Medians of synchronised wall-clock ms (`warpsense.bench.timing.time_function`); also a plain copy of each join's
output size, the memory-bound floor.
"""

from __future__ import annotations

import argparse

import torch

from warpsense.bench.timing import time_function
from warpsense.ops import upsample_concat
from warpsense.ops.reference import upsample_concat_reference


def time_join(function, x, skip, grad, device) -> tuple[float, float]:
    """Median ms of ``function(x, skip)`` forward, and forward + backward to both inputs for ``grad``."""
    with torch.no_grad():
        forward = time_function(lambda: function(x, skip), device, 30)["median_ms"]
    both = time_function(lambda: torch.autograd.grad(function(x, skip), [x, skip], grad), device, 30)["median_ms"]
    return forward, both


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--quick", action="store_true", help="one small join, for a CPU")
    args = parser.parse_args()
    device = torch.device(args.device)
    batch, height, width, w = (1, 44, 60, 8) if args.quick else (16, 352, 480, 24)
    # (channels upsampled, channels skipped, skip height, skip width) of dec1 .. dec4's inputs
    joins = [(2 * w, w, height, width), (4 * w, 2 * w, height // 2, width // 2), (6 * w, 4 * w, height // 4, width // 4),
             (8 * w, 6 * w, height // 8, width // 8)]
    if args.quick:
        joins = joins[:1]
    dtypes = (torch.bfloat16, torch.float32) if device.type == "cuda" else (torch.float32,)
    print(f"{'join':>22s} {'dtype':>9s} {'method':>8s} {'fwd ms':>8s} {'fwd+bwd ms':>10s} {'copy ms':>8s}")
    for up, kept, h, wd in joins:
        for dtype in dtypes:
            x = torch.randn(batch, up, h // 2, wd // 2, device=device, dtype=dtype)
            skip = torch.randn(batch, kept, h, wd, device=device, dtype=dtype)
            x, skip = (t.contiguous(memory_format=torch.channels_last).requires_grad_() for t in (x, skip))
            grad = torch.randn(batch, up + kept, h, wd, device=device, dtype=dtype)
            grad = grad.contiguous(memory_format=torch.channels_last)
            target = torch.empty_like(grad)
            copy = time_function(lambda target=target, grad=grad: target.copy_(grad), device, 30)["median_ms"]
            for name, function in (("warp", upsample_concat), ("torch", upsample_concat_reference)):
                forward, both = time_join(function, x, skip, grad, device)
                print(f"{str((up, kept, h, wd)):>22s} {str(dtype)[6:]:>9s} {name:>8s} {forward:8.3f} {both:10.3f}"
                      f" {copy:8.3f}", flush=True)


if __name__ == "__main__":
    main()
