"""Time a learnable lens's PSF-grid rendering, forward + backward, as a training step pays it (issue 27): the fast
path (`warpsense.optics.lens.render_pixels`) against the full-grid rendering it replaced (`pupil_psf` +
`integrate_pixels`), in one process, and count the aten calls each makes (a device-independent proxy for kernel
launches, which bound the rendering on a GPU); on CUDA also replayed as one CUDA graph. With ``--camera``, also the
whole codesign camera forward + backward at the CamVid crop (`warpsense.bench.train_suite.camera_pass`, the train
suite's camera-alone record) with each rendering, and the plain-torch baseline's Gaussian camera, eager and (CUDA)
replayed as a graph.

    python tools/bench_render.py [--lens phone_68deg] [--device cpu|cuda] [--dtype float32] [--repeats 20]
                                 [--camera] [--json F]
"""

import argparse

import torch

from warpsense.bench.timing import time_cuda_graph, time_function
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


def camera_records(name: str, device: torch.device) -> list[dict]:
    """The codesign camera's forward + backward with the rendering in place (the baseline's Gaussian camera for
    ``name`` "plain-torch baseline"), eager and, on CUDA, replayed as a graph."""
    from warpsense.bench.train_suite import camera_pass

    method, camera = ("torch_baseline", "simple") if name == "plain-torch baseline" else ("warpsense", "codesign")
    records = []
    for graph in (False, True) if device.type == "cuda" else (False,):
        timing = camera_pass(method, camera, str(device), 16, 352, 480, graph)
        records.append({"method": name, "camera": camera, "mode": "graph" if graph else "eager",
                        "device": str(device), "shape": [16, 3, 352, 480], **timing})
    return records


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lens", default="phone_68deg")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--camera", action="store_true",
                        help="also time the codesign camera (batch 16, 352 x 480) with each rendering, and the baseline's")
    parser.add_argument("--json", help="write the records here")
    args = parser.parse_args()
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    lens = Lens(read_lens_spec(args.lens), learnable=True).to(device)
    weights = None
    parameters = [p for p in lens.parameters() if p.requires_grad]
    fast = lens_module.render_pixels
    records = []
    for name, render in (("full grid (before)", full_grid), ("render_pixels", fast)):
        lens_module.render_pixels = render

        def step():
            nonlocal weights
            psf = lens.psf_grid(dtype=dtype)
            if weights is None:
                weights = torch.randn_like(psf)
            return torch.autograd.grad((psf * weights).sum(), parameters)

        records.append({"method": name, "lens": args.lens, "device": str(device), "dtype": args.dtype,
                        "grid": list(lens.spec.psf_grid), "kernel_size": lens.spec.psf_kernel_size,
                        "median_ms": time_function(step, device, args.repeats)["median_ms"],
                        "aten_calls": aten_calls(step)})
        if device.type == "cuda":  # as the training step pays it: replayed in the step's CUDA graph
            records[-1]["graph_ms"] = time_cuda_graph(step, args.repeats)["median_ms"]
        if args.camera:
            records += camera_records(name, device)
    lens_module.render_pixels = fast
    if args.camera:
        records += camera_records("plain-torch baseline", device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    print(f"{args.lens}, {name}, {args.dtype}: learnable lens PSF grid, forward + backward (median of {args.repeats})")
    rendering = [record for record in records if "aten_calls" in record]
    for record in rendering:
        graph = f", {record['graph_ms']:6.3f} ms replayed as a CUDA graph" if "graph_ms" in record else ""
        print(f"  {record['method']:<20} {record['median_ms']:9.2f} ms  {record['aten_calls']:4d} aten calls{graph}")
    print(f"  ratio {rendering[0]['median_ms'] / rendering[1]['median_ms']:.2f}x")
    for record in records:
        if "camera" in record:
            print(f"  camera {record['camera']:<9} {record['mode']:<6} rendering {record['method']:<20} "
                  f"{record['median_ms']:9.3f} ms [IQR {record['iqr_ms']:.3f}]")
    if args.json:
        write_json(args.json, records)


if __name__ == "__main__":
    main()
