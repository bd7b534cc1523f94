"""PSF convolution, forward + backward in one autograd call, every method in one run (issue 12's figures).

    python tools/bench_psf.py [--device cuda] [--json OUT] [--quick]

Times the exact varying Warp kernel (5x5 grid, K = 15) and, for one PSF, plain cuDNN conv2d (torch autograd), the
cuDNN forward with the Warp adjoints, the Warp kernel, torch FFT and `auto`, at 16 x 3 x 192 x 640 and 1 x 3 x
360 x 480 (``--quick``: one small shape, K = 7, for the CPU). Times are medians of wall-clock milliseconds with the
device synchronised; ratios are to plain cuDNN measured in the same run. Also checks the varying kernel's forward
and both gradients against the float64 torch reference.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch
import torch.nn.functional as F

from warpsense.ops import psf_conv
from warpsense.ops.psf import _conv2d_warp_gradient
from warpsense.ops.reference import psf_conv_reference


def plain_cudnn(image, psf):
    radius = psf.shape[-1] // 2
    padded = F.pad(image, (radius,) * 4, mode="replicate")
    return F.conv2d(padded, psf[:, 0, 0].flip(-1, -2).unsqueeze(1), groups=image.shape[1])


METHODS = {
    "varying_direct": lambda x, p: psf_conv(x, p, "direct"),
    "invariant_cudnn": plain_cudnn,
    "invariant_cudnn_warp_adjoints": _conv2d_warp_gradient,
    "invariant_direct": lambda x, p: psf_conv(x, p, "direct"),
    "invariant_fft": lambda x, p: psf_conv(x, p, "fft"),
    "invariant_auto": psf_conv,
}


def _median_ms(function, device: str, repeats: int) -> float:
    def sync():
        if device == "cuda":
            torch.cuda.synchronize()

    for _ in range(3):
        function()
    samples = []
    for _ in range(repeats):
        sync()
        start = time.perf_counter()
        function()
        sync()
        samples.append((time.perf_counter() - start) * 1e3)
    return statistics.median(samples)


def run(device: str = "cuda", quick: bool = False, repeats: int = 20) -> dict:
    torch.manual_seed(0)
    size = 7 if quick else 15
    shapes = [(1, 3, 40, 56)] if quick else [(16, 3, 192, 640), (1, 3, 360, 480)]
    report = {"device": torch.cuda.get_device_name() if device == "cuda" else "cpu", "torch": torch.__version__,
              "kernel_size": size, "rows": []}
    for shape in shapes:
        image = torch.rand(*shape, device=device, requires_grad=True)
        gradient = torch.rand(*shape, device=device)
        timings = {}
        for name, method in METHODS.items():
            grid = (5, 5) if name.startswith("varying") else (1, 1)
            psf = torch.rand(3, *grid, size, size, device=device)
            psf = (psf / psf.sum(dim=(-2, -1), keepdim=True)).requires_grad_()
            timings[name] = {
                "fwd_ms": _median_ms(lambda method=method, image=image, psf=psf: method(image.detach(), psf.detach()),
                                     device, repeats),
                "fwd_bwd_ms": _median_ms(lambda method=method, image=image, psf=psf, gradient=gradient:
                                         torch.autograd.grad(method(image, psf), (image, psf), gradient),
                                         device, repeats),
            }
        baseline = timings["invariant_cudnn"]["fwd_bwd_ms"]
        for name, timing in timings.items():
            report["rows"].append({"shape": list(shape), "method": name, **{k: round(v, 4) for k, v in timing.items()},
                                   "fwd_bwd_vs_cudnn": round(timing["fwd_bwd_ms"] / baseline, 3)})
    image = torch.rand(2, 3, 30, 40, device=device, dtype=torch.float64, requires_grad=True)
    psf = torch.rand(3, 5, 5, size, size, device=device, dtype=torch.float64, requires_grad=True)
    gradient = torch.rand_like(image)
    ours = torch.autograd.grad(psf_conv(image, psf, "direct"), (image, psf), gradient)
    theirs = torch.autograd.grad(psf_conv_reference(image, psf), (image, psf), gradient)
    with torch.no_grad():
        report["varying_float64_max_error"] = {
            "forward": float((psf_conv(image, psf, "direct") - psf_conv_reference(image, psf)).abs().max()),
            "grad_image": float((ours[0] - theirs[0]).abs().max()),
            "grad_psf": float((ours[1] - theirs[1]).abs().max())}
    return report


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", choices=["cpu", "cuda"])
    parser.add_argument("--quick", action="store_true", help="one small shape, K = 7 (CPU)")
    parser.add_argument("--json", metavar="OUT", help="write the report as JSON")
    args = parser.parse_args(argv)
    report = run(args.device, args.quick, repeats=3 if args.quick else 20)
    print(f"{report['device']}, K = {report['kernel_size']}; fwd+bwd in one autograd call, median ms")
    for row in report["rows"]:
        print(f"{str(tuple(row['shape'])):>18s} {row['method']:>30s} fwd {row['fwd_ms']:8.3f} fwd+bwd "
              f"{row['fwd_bwd_ms']:8.3f} ({row['fwd_bwd_vs_cudnn']:.2f}x cuDNN)")
    print("float64 max error of the varying kernel vs the torch reference:", report["varying_float64_max_error"])
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(report, handle, indent=1)
    return report


if __name__ == "__main__":
    main()
