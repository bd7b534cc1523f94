"""The exact varying PSF convolution with the column-sliding kernels against the register-tiled ones, in one process.

    python tools/bench_psf_layouts.py [--device cuda] [--json OUT] [--quick]

For each layout (``warpsense.ops.psf.SLIDING`` false / true): the forward, the image adjoint and forward + both
adjoints at the CamVid recipe's shape (16 x 3 x 352 x 480, 5 x 5 grid, K = 15); the codesign camera forward +
backward (`warpsense.bench.train_suite.camera_pass`); batch-1 latency at 192 x 640 (`latency`), the baseline's
included. Medians of synchronised wall-clock ms, eager and (CUDA) replayed as a CUDA graph. Also the two layouts'
largest differences.
"""

from __future__ import annotations

import argparse

import torch

import warpsense.ops.psf as psf_ops
from warpsense.bench.timing import time_cuda_graph, time_function
from warpsense.bench.train_suite import camera_pass, latency
from warpsense.files import write_json
from warpsense.optics import Lens


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json")
    parser.add_argument("--quick", action="store_true", help="a small shape, for a CPU")
    args = parser.parse_args()
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    batch, height, width = (1, 64, 96) if args.quick else (16, 352, 480)
    torch.manual_seed(0)
    grid = Lens.from_json("phone_68deg").psf_grid().to(device)
    start = (grid.shape[-1] - 15) // 2
    psf = grid[..., start:start + 15, start:start + 15].float()
    psf = (psf / psf.sum(dim=(-2, -1), keepdim=True)).requires_grad_()
    image = torch.rand(batch, 3, height, width, device=device, requires_grad=True)
    weights = torch.randn(batch, 3, height, width, device=device)
    repeats = 5 if args.quick else 30
    records, results = [], {}

    def record(layout, name, function, graphs=(False, True) if cuda else (False,)):
        for graph in graphs:
            timing = time_cuda_graph(function, repeats) if graph else time_function(function, device, repeats)
            records.append({"layout": layout, "case": name, "mode": "graph" if graph else "eager", **timing})
            print(f"{layout:>9s} {name:>32s} {'graph' if graph else 'eager':>5s} {timing['median_ms']:9.3f} ms "
                  f"[IQR {timing['iqr_ms']:.3f}]", flush=True)

    for layout, sliding in (("tiled", False), ("sliding", True)):
        psf_ops.SLIDING = sliding
        out = psf_ops.psf_conv(image, psf, "direct")
        results[layout] = [out.detach(), *torch.autograd.grad((out * weights).sum(), [image, psf])]
        cells = psf_ops.node_cells(psf.detach())
        record(layout, "forward", lambda: psf_ops._psf_conv_cells(image.detach(), cells, 5, 5))
        record(layout, "image adjoint", lambda: psf_ops._psf_backward_image(weights, cells, 5, 5))
        record(layout, "forward + both adjoints",
               lambda: torch.autograd.grad((psf_ops.psf_conv(image, psf, "direct") * weights).sum(), [image, psf]),
               graphs=(False,))  # autograd's engine outside the camera does not capture here; the camera's does
        if not args.quick:
            for graph in ((False, True) if cuda else (False,)):
                timing = camera_pass("warpsense", "codesign", args.device, 16, 352, 480, graph)
                records.append({"layout": layout, "case": "codesign camera fwd+bwd", "mode": "graph" if graph
                                else "eager", **timing})
                print(f"{layout:>9s} {'codesign camera fwd+bwd':>32s} {'graph' if graph else 'eager':>5s} "
                      f"{timing['median_ms']:9.3f} ms", flush=True)
                timing = latency("warpsense", "codesign", args.device, 192, 640, graph)
                records.append({"layout": layout, "case": "latency codesign 192x640", "mode": "graph" if graph
                                else "eager", **timing})
                print(f"{layout:>9s} {'latency codesign 192x640':>32s} {'graph' if graph else 'eager':>5s} "
                      f"{timing['median_ms']:9.3f} ms", flush=True)
    if not args.quick:
        for graph in ((False, True) if cuda else (False,)):
            timing = camera_pass("torch_baseline", "simple", args.device, 16, 352, 480, graph)
            records.append({"layout": "baseline", "case": "gaussian camera fwd+bwd", "mode": "graph" if graph
                            else "eager", **timing})
            print(f"{'baseline':>9s} {'gaussian camera fwd+bwd':>32s} {'graph' if graph else 'eager':>5s} "
                  f"{timing['median_ms']:9.3f} ms", flush=True)
            timing = latency("torch_baseline", "simple", args.device, 192, 640, graph)
            records.append({"layout": "baseline", "case": "latency baseline 192x640", "mode": "graph" if graph
                            else "eager", **timing})
            print(f"{'baseline':>9s} {'latency baseline 192x640':>32s} {'graph' if graph else 'eager':>5s} "
                  f"{timing['median_ms']:9.3f} ms", flush=True)
    differences = {name: float((a - b).abs().max()) for name, a, b in
                   zip(("output", "image gradient", "psf gradient"), results["tiled"], results["sliding"])}
    print("largest differences sliding - tiled:", differences)
    if args.json:
        write_json(args.json, {"device": torch.cuda.get_device_name(device) if cuda else "cpu", "records": records,
                               "differences": differences})


if __name__ == "__main__":
    main()
