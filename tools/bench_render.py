"""Time a learnable lens's PSF-grid rendering, forward + backward, as a training step pays it (issue 27): the fast
path (`warpsense.optics.lens.render_pixels`) against the full-grid rendering it replaced (`pupil_psf` +
`integrate_pixels`), in one process, and count the aten calls each makes (a device-independent proxy for kernel
launches, which bound the rendering on a GPU).

    python tools/bench_render.py [--lens phone_68deg] [--device cpu|cuda] [--dtype float32] [--repeats 20] [--json F]
"""

import argparse
import statistics
import time

import torch

from warpsense.files import write_json
from warpsense.optics import integrate_pixels, pupil_psf
from warpsense.optics import lens as lens_module
from warpsense.optics.lens import Lens, read_lens_spec


def full_grid(coefficients, noll, azimuth, pupil_samples, zero_padding, size, factor, pupil_radius=None):
    """The rendering before `render_pixels`: each node's full M x M pupil, centred FFTs, the box filter by FFT."""
    return integrate_pixels(pupil_psf(coefficients, noll, azimuth, pupil_samples, zero_padding, pupil_radius),
                            size, factor)


def aten_calls(step) -> int:
    """Outermost aten calls of one ``step()`` that are not views or allocations."""
    from torch.profiler import ProfilerActivity, profile

    free = ("view", "as_strided", "empty", "reshape", "expand", "transpose", "permute", "unsqueeze", "squeeze",
            "slice", "select", "detach", "alias", "result_type", "resize_", "t", "numpy_T", "real", "imag", "to",
            "lift_fresh", "view_as_real", "view_as_complex", "_unsafe_view", "flatten", "resolve_conj", "resolve_neg")
    with profile(activities=[ProfilerActivity.CPU]) as trace:
        step()
    count = 0
    for event in trace.events():
        if not event.name.startswith("aten::") or event.name[6:].split(".")[0] in free:
            continue
        parent = event.cpu_parent
        while parent is not None and not parent.name.startswith("aten::"):
            parent = parent.cpu_parent
        count += parent is None
    return count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lens", default="phone_68deg")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--json", help="write the records here")
    args = parser.parse_args()
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    lens = Lens(read_lens_spec(args.lens), learnable=True).to(device)
    weights = None
    fast = lens_module.render_pixels
    records = []
    for name, render in (("full grid (before)", full_grid), ("render_pixels", fast)):
        lens_module.render_pixels = render

        def step():
            nonlocal weights
            psf = lens.psf_grid(dtype=dtype)
            if weights is None:
                weights = torch.randn_like(psf)
            (psf * weights).sum().backward()

        for _ in range(3):
            step()
        times = []
        for _ in range(args.repeats):
            if device.type == "cuda":
                torch.cuda.synchronize()
            started = time.perf_counter()
            step()
            if device.type == "cuda":
                torch.cuda.synchronize()
            times.append((time.perf_counter() - started) * 1e3)
        records.append({"method": name, "lens": args.lens, "device": str(device), "dtype": args.dtype,
                        "grid": list(lens.spec.psf_grid), "kernel_size": lens.spec.psf_kernel_size,
                        "median_ms": statistics.median(times), "aten_calls": aten_calls(step)})
    lens_module.render_pixels = fast
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    print(f"{args.lens}, {name}, {args.dtype}: learnable lens PSF grid, forward + backward (median of {args.repeats})")
    for record in records:
        print(f"  {record['method']:<20} {record['median_ms']:9.2f} ms  {record['aten_calls']:4d} aten calls")
    print(f"  ratio {records[0]['median_ms'] / records[1]['median_ms']:.2f}x")
    if args.json:
        write_json(args.json, records)


if __name__ == "__main__":
    main()
