"""Batch norm + ReLU (the network's Warp op) forward + backward at the recipe's full-resolution stage, and the
recipe's training step alone, for an A/B of two code trees in one call (run this file from each tree's root).

    python docs/records/step/batchnorm/ab.py NAME

Prints one JSON line: NAME, the op's median ms (16 x 16 x 352 x 480 bfloat16 channels-last, forward + backward to x,
weight and bias, replayed as one CUDA graph, `warpsense.bench.timing.time_cuda_graph`, median of 50) and the step's
img/s (`docs/records/step/concurrency/concurrency.py`'s `timed`, one copy, 60 steps after 8).
"""

import json
import sys
from pathlib import Path

import torch

from warpsense.bench.timing import time_cuda_graph
from warpsense.ops import batch_norm_relu

sys.path.insert(0, str(Path("docs/records/step/concurrency").resolve()))
import concurrency  # noqa: E402

torch.manual_seed(0)
x = torch.randn(16, 16, 352, 480, device="cuda", dtype=torch.bfloat16).to(memory_format=torch.channels_last)
x.requires_grad_()
weight = torch.rand(16, device="cuda", requires_grad=True)
bias = torch.rand(16, device="cuda", requires_grad=True)
mean, var = torch.zeros(16, device="cuda"), torch.ones(16, device="cuda")
grad = torch.randn_like(x)


def step():
    y = batch_norm_relu(x, weight, bias, mean, var, 0.1, 1e-5)
    return torch.autograd.grad(y, (x, weight, bias), grad)


op = time_cuda_graph(step)
rate = concurrency.timed(1, concurrency.BATCH, 60, 8)
print(json.dumps({"tree": sys.argv[1], "bn_fwd_bwd_ms": op["median_ms"], "bn_iqr_ms": op["iqr_ms"],
                  "step_images_per_s": rate}), flush=True)
