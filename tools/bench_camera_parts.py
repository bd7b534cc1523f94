"""The codesign camera's forward + backward in parts, against the plain-torch baseline's Gaussian camera (issue 27's
"camera <= Gaussian" item): what each part costs, and the floor of the PSF convolution's arithmetic.

    python tools/bench_camera_parts.py [--device cuda] [--size 352x480] [--batch 16] [--repeats 50]
        [--peak-tops 33.5] [--json OUT]

Each part runs forward + backward to what learns in the joint phase, timed as one CUDA graph's replay on CUDA
(eagerly on a CPU), median ms:
- camera: the whole codesign camera (`camvid_codesign`'s; `train_suite.camera_pass`);
- rendering: the PSF grid of a learnable lens built from the same lens file, alone (float32 pupil FFTs, as the
  config renders them), backward to its Zernike coefficients;
- psf_conv: the spatially varying convolution with a fixed grid of that shape, forward + gradient to the grid
  (the radiance is data: the camera's backward needs no image gradient);
- psf_forward: the convolution's forward alone;
- baseline: the plain-torch baseline's camera (7 x 7 Gaussian by conv2d, eager sensor ops).

The floor is the convolution's FP32 arithmetic at the device's peak instruction rate (``--peak-tops``, tera
instructions per second, an FMA counting as one; 33.5 for the H100 SXM: 132 SMs x 128 lanes x 1.98 GHz): per output
and tap, 2 in the forward (the corner PSFs mixed along y, then the accumulation: `kernels/psf.py`'s count where a
thread's window lies in one cell) and 3 in the PSF gradient (the product, its two sums), K^2 taps, B x 3 x H x W
outputs. Loads, index arithmetic and the cell borders come on top, so no kernel of this algorithm reaches it.
"""

from __future__ import annotations

import argparse
import sys

import torch

from warpsense.bench import parse_size
from warpsense.bench.timing import time_cuda_graph, time_function
from warpsense.files import write_json

OPS_PER_TAP = {"forward": 2, "psf_gradient": 3}  # FP32 instructions per output and tap (module docstring)


def timed(step, device: torch.device, repeats: int) -> dict:
    """``step()``'s median ms [IQR]: replayed as a CUDA graph on CUDA, eager otherwise."""
    if device.type == "cuda":
        return time_cuda_graph(step, repeats)
    return time_function(step, device, repeats, warmup=1)


def parts(device: torch.device, batch: int, height: int, width: int, repeats: int) -> dict:
    """name -> timing (`timed`) of each part in the module docstring, and the PSF grid's shape."""
    from warpsense.bench.train_suite import camera_pass
    from warpsense.config import load_config
    from warpsense.ops import psf_conv
    from warpsense.optics.lens import Lens

    config = load_config("camvid_codesign", [])
    lens = Lens.from_json(config.optics.lens, learnable=True).to(device)
    coefficients = [p for p in lens.parameters() if p.requires_grad]
    render_dtype = getattr(torch, config.optics.render_precision)
    grid = lens.psf_grid(dtype=render_dtype).float().detach()
    grid_weights = torch.randn_like(grid)
    psf = grid.clone().requires_grad_(True)
    generator = torch.Generator(device="cpu").manual_seed(0)
    radiance = (torch.rand(batch, 3, height, width, generator=generator) * 0.5).to(device)
    out_weights = torch.randn(batch, 3, height, width, generator=generator).to(device)

    def rendering():
        rendered = lens.psf_grid(dtype=render_dtype).float()
        return torch.autograd.grad((rendered * grid_weights).sum(), coefficients)

    def convolution():
        return torch.autograd.grad((psf_conv(radiance, psf) * out_weights).sum(), [psf])

    def forward():
        with torch.no_grad():
            return psf_conv(radiance, grid)

    graph = device.type == "cuda"
    results = {
        "camera": camera_pass("warpsense", "codesign", str(device), batch, height, width, graph),
        "rendering": timed(rendering, device, repeats),
        "psf_conv": timed(convolution, device, repeats),
        "psf_forward": timed(forward, device, repeats),
        "baseline": camera_pass("torch_baseline", "simple", str(device), batch, height, width, graph),
    }
    return results, list(grid.shape)


def floor_ms(outputs: int, kernel_size: int, peak_tops: float) -> dict:
    """The convolution's arithmetic at ``peak_tops`` (module docstring), ms per pass."""
    return {name: outputs * kernel_size ** 2 * ops / (peak_tops * 1e12) * 1e3 for name, ops in OPS_PER_TAP.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", choices=("cpu", "cuda"))
    parser.add_argument("--size", default="352x480", help="HxW of the radiance")
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--peak-tops", type=float, default=33.5,
                        help="FP32 instructions per second of the device, in tera (an FMA is one)")
    parser.add_argument("--json", metavar="OUT")
    args = parser.parse_args(argv)
    try:
        height, width = parse_size(args.size, "--size", "352x480")
    except ValueError as error:
        parser.error(str(error))
    if args.peak_tops <= 0:
        parser.error(f"--peak-tops must be > 0, got {args.peak_tops}")
    device = torch.device(args.device)
    results, shape = parts(device, args.batch, height, width, args.repeats)
    outputs = args.batch * 3 * height * width
    floor = floor_ms(outputs, shape[-1], args.peak_tops)
    median = {name: timing["median_ms"] for name, timing in results.items()}
    rest = median["camera"] - median["rendering"] - median["psf_conv"]
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    mode = "graph replay" if device.type == "cuda" else "eager"
    print(f"{name}, batch {args.batch}, 3 x {height} x {width}, PSF grid {shape}, forward + backward, {mode}, "
          f"median ms [IQR]")
    for part, timing in results.items():
        print(f"  {part:<12} {timing['median_ms']:8.3f} [{timing['iqr_ms']:.3f}]")
    print(f"  camera - rendering - psf_conv (sensor, normalisation, padding): {rest:.3f}")
    print(f"  camera / baseline {median['camera'] / median['baseline']:.2f}; psf_conv alone / baseline "
          f"{median['psf_conv'] / median['baseline']:.2f}")
    print(f"  floor at {args.peak_tops} T instructions/s: forward {floor['forward']:.3f}, PSF gradient "
          f"{floor['psf_gradient']:.3f}, both {sum(floor.values()):.3f} (psf_conv measured "
          f"{median['psf_conv']:.3f}: {sum(floor.values()) / median['psf_conv']:.0%} of peak)")
    if args.json:
        write_json(args.json, {"device": name, "mode": mode, "batch": args.batch, "size": [height, width],
                               "psf_grid": shape, "peak_tops": args.peak_tops, "parts": results,
                               "rest_ms": rest, "floor_ms": floor})
    return 0


if __name__ == "__main__":
    sys.exit(main())
