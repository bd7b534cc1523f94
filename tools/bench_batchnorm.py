"""The fused batch norm + ReLU (`warpsense.ops.batch_norm_relu`) against torch's batch norm and ReLU, over every
batch norm + ReLU of the recipe's network (DSUNet width 24 with the pyramid context, channels-last, bf16) at its
training shape (batch 16, 352 x 480), all layers in one CUDA graph, forward and forward + backward.

    python tools/bench_batchnorm.py [--device cuda] [--threads N] [--profile FILE] [--json OUT]

``--threads`` replaces the op's threads per launch (a tuning aid). `kernels/batchnorm.py`'s UNROLL is read when its
kernels are declared, at import, so it is tuned by editing the source (tools/device/README.md), not from here.
Medians of graph-replay ms (`warpsense.bench.timing.time_cuda_graph`; eager wall-clock ms on a CPU, one small
layer); also the bytes the fused op moves over the time.
"""

from __future__ import annotations

import argparse
import json

import torch
from torch.nn import functional as F

from warpsense.bench.timing import time_cuda_graph, time_function, write_kernel_table
from warpsense.models import build_model
from warpsense.ops import batch_norm_relu
from warpsense.ops import batchnorm as op_module


def layer_shapes(batch: int, height: int, width: int) -> list[tuple[int, int, int, int]]:
    """The inputs [B, C, H, W] of the recipe network's batch norms that a ReLU follows (the context module's is
    not: it adds to a residual)."""
    network = build_model("dsunet", in_channels=1, num_classes=11, width=24, context="pyramid")
    shapes = []
    for name, module in network.named_modules():
        if isinstance(module, torch.nn.BatchNorm2d) and not name.startswith("context"):
            module.register_forward_pre_hook(lambda m, inputs: shapes.append((batch, *inputs[0].shape[1:])))
    with torch.no_grad():
        network.eval()(torch.zeros(1, 1, height, width))
    return shapes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--threads", type=int, help="threads per reduction launch on CUDA for this process")
    parser.add_argument("--profile", metavar="FILE", help="the fused op's kernels by GPU time (forward + backward)")
    parser.add_argument("--json", metavar="OUT")
    args = parser.parse_args()
    if args.threads:
        op_module._THREADS["cuda"] = args.threads
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    shapes = layer_shapes(16, 352, 480) if cuda else layer_shapes(1, 32, 48)[:1]
    dtype = torch.bfloat16 if cuda else torch.float32
    layers = []
    for shape in shapes:
        x = torch.randn(shape, device=device).to(dtype).contiguous(memory_format=torch.channels_last)
        channels = shape[1]
        params = [torch.rand(channels, device=device) + 0.5, torch.randn(channels, device=device)]
        layers.append((x.requires_grad_(), [p.requires_grad_() for p in params],
                       [torch.zeros(channels, device=device), torch.ones(channels, device=device)],
                       torch.randn_like(x)))

    def torch_layer(x, params, buffers):
        return F.relu(F.batch_norm(x, *buffers, *params, training=True))

    def fused_layer(x, params, buffers):
        return batch_norm_relu(x, *params, *buffers)

    def forward(layer):
        return lambda: [layer(x, params, buffers) for x, params, buffers, _ in layers]

    def both(layer):
        def run():
            for x, params, buffers, grad in layers:
                torch.autograd.grad(layer(x, params, buffers), [x, *params], grad)
        return run

    timer = time_cuda_graph if cuda else (lambda function: time_function(function, device, 10))
    elements = sum(torch.Size(shape).numel() for shape in shapes)
    record = {"device": torch.cuda.get_device_name(device) if cuda else "cpu", "layers": len(shapes),
              "elements": elements, "dtype": str(dtype)[6:], "unroll": op_module.kernels.UNROLL,
              "threads": op_module._THREADS.get("cuda")}
    for name, layer in (("torch", torch_layer), ("fused", fused_layer)):
        record[f"{name}_forward_ms"] = timer(forward(layer))["median_ms"]
        record[f"{name}_forward_backward_ms"] = timer(both(layer))["median_ms"]
    # the fused op's traffic: x read twice and y written forward; dy and x read twice and dx written backward
    item = torch.empty((), dtype=dtype).element_size()
    record["fused_forward_tb_s"] = 3 * elements * item / record["fused_forward_ms"] / 1e9
    record["fused_forward_backward_tb_s"] = 8 * elements * item / record["fused_forward_backward_ms"] / 1e9
    print(json.dumps(record), flush=True)
    if args.profile:
        write_kernel_table(both(fused_layer), device, args.profile)
    if args.json:
        with open(args.json, "w") as file:
            json.dump(record, file, indent=1)


if __name__ == "__main__":
    main()
