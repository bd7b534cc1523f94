"""`warpsense bench --suite accuracy`: error against run time, for every kernel and for the lens model's
discretisation.

Errors are measured against a float64 reference computed by a different implementation than the one measured
(the direct torch blend for the PSF convolution, the eager torch formulas for the CFA and the quantizer):

- ``max_rel_err`` = max |y - r| / max |r| (normwise, infinity norm);
- ``l2_rel_err`` = ||y - r||_2 / ||r||_2;
- ``p99_rel_err`` = the 99th percentile over values of |y - r| / max(|r|, 1e-12 max |r|): pointwise, so it sees
  the dark pixels that both norms hide;
- the quantizer's ``code_flip_rate``: the fraction of codes that differ from the codes computed in float64 from the
  same float32 input.

Scenes: white noise U(0, 1); real CamVid frames (sRGB decoded to linear, resized to the scene size); an HDR night
scene (lamps at 1e3 on a 1e-6 background: 9 decades, the case where an FFT's rounding, relative to the frame
maximum, buries the dark pixels).

Times come from `torch.utils.benchmark.Timer.blocked_autorange` (medians; the device synchronised by the timer; the
thread count is recorded and printed): the forward, the backward alone (its graph built outside the timed region and
retained) and forward + backward in one autograd call. Warp's CPU backend runs each kernel on one thread whatever
that count.

The lens (phone_80deg) is studied one axis at a time, the others at the lens file's values, each setting rendered
and convolved in float64 by the same FFT blend as its converged reference, so the error is the discretisation
alone: the PSF grid (reference 17 x 17), the kernel size K (crops of a K = 127 rendering, whose energy outside is
shown; 1 - 1e-6 of the energy is out of reach for a hard-edged pupil, whose encircled energy converges only as 1 / r),
the pupil samples D (reference 256) and the pixel-integration samples (reference 15). Each record also holds its
error against the next finer setting, so the convergence is visible in the table. Its time is what a training step
pays for the setting: rendering the PSF grid plus the Warp convolution's forward + backward in float32.

Every record is printed, by `format_record`, from the dict that goes into the JSON.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch.utils import benchmark

from warpsense.data.color import srgb_to_linear
from warpsense.ops import cfa_mosaic, psf_conv, quantize_ste
from warpsense.ops.psf import psf_conv_conv2d, psf_conv_fft, psf_conv_patch
from warpsense.ops.reference import (
    cfa_mosaic_reference,
    psf_conv_blend_fft,
    psf_conv_reference,
    quantize_reference,
)

POINTWISE_FLOOR = 1e-12  # of max |r|: below it a reference value counts as zero in the pointwise relative error
QUANTIZER_BITS = (8, 10, 12, 14, 16, 20, 24)
LENS_NAME = "phone_80deg"
# (axis, lens-spec field, settings timed, converged reference)
LENS_AXES = {
    "psf_grid": ("psf_grid", (1, 3, 5, 7, 9, 13), 17),
    "kernel_size": ("psf_kernel_size", (5, 9, 15, 21, 31, 41, 63), 127),
    "pupil_samples": ("pupil_samples", (16, 24, 32, 48, 64, 96, 128, 192), 256),
    "pixel_integration": ("oversampling", (1, 2, 3, 4, 5, 7, 9), 15),
}
QUICK_LENS_AXES = {
    "psf_grid": ("psf_grid", (1, 3, 5), 9),
    "kernel_size": ("psf_kernel_size", (5, 9, 15), 31),
    "pupil_samples": ("pupil_samples", (16, 32), 64),
    "pixel_integration": ("oversampling", (1, 3), 7),
}


def error_norms(output: torch.Tensor, reference: torch.Tensor) -> dict:
    """The three relative errors of ``output`` against ``reference`` (float64, any shape)."""
    output, reference = output.detach().double(), reference.detach().double()
    difference = (output - reference).abs()
    scale = reference.abs().max()
    pointwise = difference / reference.abs().clamp_min(POINTWISE_FLOOR * float(scale))
    return {"max_rel_err": float(difference.max() / scale), "l2_rel_err": float(difference.norm() / reference.norm()),
            "p99_rel_err": float(torch.quantile(pointwise.flatten()[: 1 << 24], 0.99))}


def code_flip_rate(output: torch.Tensor, raw: torch.Tensor, bits: int, white_level: float = 1.0) -> float:
    """Fraction of the quantizer's codes (output / w * (2^b - 1), rounded) that differ from the codes computed in
    float64 from the same input (``raw``, as the op saw it)."""
    levels = (1 << bits) - 1
    exact = torch.floor(raw.detach().double().clamp(0, white_level) / white_level * levels + 0.5)
    codes = torch.round(output.detach().double() / white_level * levels)
    return float((codes != exact).double().mean())


def make_scenes(height: int, width: int, device: str, camvid_root: str | None = None, frames: int = 2) -> dict:
    """{name: [B, 3, H, W] float64 linear radiance}; "camvid" only when ``camvid_root`` is given."""
    generator = torch.Generator().manual_seed(0)
    scenes = {"white_noise": torch.rand(1, 3, height, width, generator=generator, dtype=torch.float64)}
    if camvid_root:
        from warpsense.data.datasets import CamVid

        dataset = CamVid(camvid_root, "val", limit=frames)
        images = torch.stack([dataset[index][0] for index in range(len(dataset))])
        linear = srgb_to_linear(images).double()
        scenes["camvid"] = F.interpolate(linear, size=(height, width), mode="bilinear", antialias=True,
                                         align_corners=False).clamp_min(0)
    night = 1e-6 * (1 + 0.5 * torch.rand(1, 3, height, width, generator=generator, dtype=torch.float64))
    yy, xx = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                            indexing="ij")
    for _ in range(max(4, height * width // 2000)):  # street lamps: discs of radius 1.5-3 px at 1e3
        y, x, radius = (torch.rand(3, generator=generator, dtype=torch.float64) * torch.tensor([height, width, 1.5])
                        + torch.tensor([0, 0, 1.5])).tolist()
        night[..., (yy - y) ** 2 + (xx - x) ** 2 <= radius**2] = 1e3
    scenes["hdr"] = night
    return {name: scene.to(device) for name, scene in scenes.items()}


class AccuracyBench:
    """Collects the records; each one is printed (`format_record`) once complete."""

    def __init__(self, device: str, min_run_time: float):
        self.device, self.min_run_time, self.threads, self.records = device, min_run_time, torch.get_num_threads(), []

    def measure(self, function) -> float:
        """Median milliseconds per call of ``function()`` (after two untimed calls: compilation, cudnn tuning)."""
        function(), function()
        timer = benchmark.Timer(stmt="function()", globals={"function": function}, num_threads=self.threads)
        return timer.blocked_autorange(min_run_time=self.min_run_time).median * 1e3

    def times(self, function, inputs: list[torch.Tensor]) -> dict:
        """Forward, backward alone and forward + backward (ms) of ``function(*inputs)``; backward times are None
        when no input needs a gradient."""
        with torch.no_grad():
            forward = self.measure(lambda: function(*inputs))
        wanted = [x for x in inputs if x.requires_grad]
        if not wanted:
            return {"fwd_ms": forward, "bwd_ms": None, "fwd_bwd_ms": None}
        output = function(*inputs)
        grad = torch.ones_like(output)
        backward = self.measure(lambda: torch.autograd.grad(output, wanted, grad, retain_graph=True))
        both = self.measure(lambda: torch.autograd.grad(function(*inputs), wanted, grad))
        return {"fwd_ms": forward, "bwd_ms": backward, "fwd_bwd_ms": both}

    def add(self, **record) -> dict:
        record = {"suite": "accuracy", "device": self.device, "threads": self.threads, **record}
        self.records.append(record)
        print(format_record(record), flush=True)
        return record


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def format_record(record: dict) -> str:
    """One console / table line of an accuracy record."""
    errors = (f"flips {_fmt(record.get('code_flip_rate'), '9.3g')}" if "code_flip_rate" in record else
              f"max {_fmt(record.get('max_rel_err'), '9.3g')}  l2 {_fmt(record.get('l2_rel_err'), '9.3g')}  "
              f"p99 {_fmt(record.get('p99_rel_err'), '9.3g')}")
    if record["kernel"].startswith("lens_"):
        finer = f"  vs next finer {_fmt(record.get('vs_next_finer'), '9.3g')}"
        outside = f"  energy outside {record['energy_outside']:.3g}" if "energy_outside" in record else ""
        cost = (f"render {_fmt(record.get('render_ms'), '9.3f')} + conv fwd+bwd "
                f"{_fmt(record.get('conv_fwd_bwd_ms'), '9.3f')} ms" if not record["converged"] else
                "(converged reference)")
        return (f"{record['kernel']:>22s} {record['method']:>22s} {record['scene']:>11s}  {errors}{finer}  "
                f"{cost}{outside}")
    return (f"{record['kernel']:>22s} {record['method']:>22s} {record['scene']:>11s}  {errors}  "
            f"fwd {_fmt(record.get('fwd_ms'), '9.3f')}  bwd {_fmt(record.get('bwd_ms'), '9.3f')}  "
            f"fwd+bwd {_fmt(record.get('fwd_bwd_ms'), '9.3f')} ms")


def run_accuracy_suite(device: str, quick: bool, camvid_root: str | None = None) -> list[dict]:
    """All kernels and lens axes; scenes of 64 x 96 (quick), 192 x 256 (CPU) or 352 x 480 (CUDA)."""
    torch.manual_seed(0)
    height, width = (64, 96) if quick else ((352, 480) if device == "cuda" else (192, 256))
    bench = AccuracyBench(device, min_run_time=0.05 if quick else 0.5)
    scenes = make_scenes(height, width, device, camvid_root)
    print(f"accuracy suite on {device}: scenes {sorted(scenes)} at {height} x {width}, torch threads "
          f"{bench.threads}", flush=True)
    _psf_methods(bench, scenes)
    _pointwise_kernels(bench, scenes, quick)
    _lens_axes(bench, scenes, QUICK_LENS_AXES if quick else LENS_AXES)
    return bench.records


def _lens(device: str, field: str | None = None, value=None):
    """The studied lens, with one spec field set (a PSF grid value G means G x G)."""
    from warpsense.optics import Lens

    lens = Lens.from_json(LENS_NAME)
    if field is not None:
        setattr(lens.spec, field, (value, value) if field == "psf_grid" else value)
    return lens.to(device)


def _render_time(bench: AccuracyBench, lens) -> float:
    with torch.no_grad():
        return bench.measure(lens.psf_grid)


def _psf_methods(bench: AccuracyBench, scenes: dict) -> None:
    """The varying convolution (the lens's 5 x 5 grid, K = 15) and the invariant one (its centre PSF)."""
    varying64 = _lens(bench.device).psf_grid()
    invariant64 = varying64[:, 2:3, 2:3].contiguous()
    cases = {
        "psf_conv": (varying64, psf_conv_reference, {
            "warp": lambda x, p: psf_conv(x, p, "direct"),
            "warp_bf16_image": lambda x, p: psf_conv(x.bfloat16(), p, "direct"),
            "torch_blend": psf_conv_reference,
            "torch_patch_approx": psf_conv_patch,
        }),
        "psf_conv_invariant": (invariant64, lambda x, p: psf_conv_conv2d(x, p[:, 0, 0]), {
            "warp": lambda x, p: psf_conv(x, p, "direct"),
            "conv2d": lambda x, p: psf_conv_conv2d(x, p[:, 0, 0]),
            "fft": lambda x, p: psf_conv_fft(x, p[:, 0, 0]),
        }),
    }
    for kernel, (psf64, reference_function, methods) in cases.items():
        references = {name: reference_function(scene, psf64) for name, scene in scenes.items()}
        psf32 = psf64.float().requires_grad_()
        for method, function in methods.items():
            timing = bench.times(function, [scenes["white_noise"].float().requires_grad_(), psf32])
            for name, scene in scenes.items():
                with torch.no_grad():
                    output = function(scene.float(), psf64.float())
                bench.add(kernel=kernel, method=method, scene=name, dtype="float32", shape=list(scene.shape),
                          **error_norms(output, references[name]), **timing)


def _pointwise_kernels(bench: AccuracyBench, scenes: dict, quick: bool) -> None:
    """The CFA mosaic (Warp against torch, both float32) and the quantizer's code flips at each bit depth."""
    phi64 = torch.rand(2, 2, 3, dtype=torch.float64, device=bench.device)
    methods = {"warp": cfa_mosaic, "torch": cfa_mosaic_reference}
    for method, function in methods.items():
        timing = bench.times(function, [scenes["white_noise"].float().requires_grad_(), phi64.float().requires_grad_()])
        for name, scene in scenes.items():
            with torch.no_grad():
                output = function(scene.float(), phi64.float())
            bench.add(kernel="cfa_mosaic", method=method, scene=name, dtype="float32", shape=list(scene.shape),
                      **error_norms(output, cfa_mosaic_reference(scene, phi64)), **timing)
    # the quantizer sees each scene scaled to [0, 1] (the HDR night mostly quantizes to 0: that is its point)
    raws = {name: (scene[:, 1:2] / scene[:, 1:2].max()).float() for name, scene in scenes.items()}
    quantizers = {"warp": quantize_ste, "torch_float32": quantize_reference}
    for bits in (QUANTIZER_BITS[:3] + QUANTIZER_BITS[-2:]) if quick else QUANTIZER_BITS:
        for method, function in quantizers.items():
            timing = bench.times(lambda r, function=function, bits=bits: function(r, bits),
                                 [raws["white_noise"].clone().requires_grad_()])
            for name, raw in raws.items():
                with torch.no_grad():
                    output = function(raw, bits)
                bench.add(kernel="quantize_ste", method=f"{method}_{bits}bit", scene=name, dtype="float32",
                          shape=list(raw.shape), code_flip_rate=code_flip_rate(output, raw, bits), **timing)


def _lens_axes(bench: AccuracyBench, scenes: dict, axes: dict) -> None:
    for axis, (field, settings, converged) in axes.items():
        if axis == "kernel_size":
            _kernel_size_axis(bench, scenes, settings, converged)
            continue
        values = list(settings) + [converged]
        lenses = {value: _lens(bench.device, field, value) for value in values}
        psfs = {value: lens.psf_grid() for value, lens in lenses.items()}
        _lens_records(bench, scenes, axis, values, psfs, {value: _render_time(bench, lenses[value]) for value in
                                                           settings})


def _kernel_size_axis(bench: AccuracyBench, scenes: dict, settings, converged: int) -> None:
    """K: each kernel the renormalised centre crop of one K = ``converged`` rendering (the same pupil sampling for
    every K), with the energy each leaves outside that window."""
    wide = _lens(bench.device, "psf_kernel_size", converged).psf_grid()
    psfs, outside = {}, {}
    for size in list(settings) + [converged]:
        start = (converged - size) // 2
        window = wide[..., start : start + size, start : start + size]
        outside[size] = float((1 - window.sum(dim=(-2, -1))).amax())
        psfs[size] = window / window.sum(dim=(-2, -1), keepdim=True)
    render = {size: _render_time(bench, _lens(bench.device, "psf_kernel_size", size)) for size in settings}
    _lens_records(bench, scenes, "kernel_size", list(settings) + [converged], psfs, render,
                  {size: {"energy_outside": outside[size]} for size in outside})


def _lens_records(bench: AccuracyBench, scenes: dict, axis: str, values: list, psfs: dict, render_ms: dict,
                  extra: dict | None = None) -> None:
    """Image errors of each setting against the converged one (the last value) and against the next finer one."""
    images = {value: {name: psf_conv_blend_fft(scene, psfs[value]) for name, scene in scenes.items()}
              for value in values}
    for position, value in enumerate(values):
        timing = {}
        if value in render_ms:
            image32 = scenes["white_noise"].float().requires_grad_()
            psf32 = psfs[value].float().requires_grad_()
            conv = bench.times(lambda x, p: psf_conv(x, p, "direct"), [image32, psf32])["fwd_bwd_ms"]
            timing = {"render_ms": render_ms[value], "conv_fwd_bwd_ms": conv, "fwd_bwd_ms": render_ms[value] + conv}
        for name in scenes:
            record = {"kernel": f"lens_{axis}", "method": f"{axis}={value}", "setting": value, "scene": name,
                      "dtype": "float64", "shape": list(scenes[name].shape), "converged": value == values[-1],
                      **error_norms(images[value][name], images[values[-1]][name]), **timing,
                      **(extra or {}).get(value, {})}
            if position + 1 < len(values):
                record["vs_next_finer"] = error_norms(images[value][name], images[values[position + 1]][name])[
                    "l2_rel_err"]
            bench.add(**record)


# ---------------------------------------------------------------------------------------------------------- plots

def pareto_frontier(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The points no other point beats in both time and error (faster or equal, and strictly less error), by time."""
    frontier, best = [], math.inf
    for time_ms, error in sorted(points):
        if error < best:
            frontier.append((time_ms, error))
            best = error
    return frontier


def plot_accuracy(records: list[dict], path: str | Path, scene: str | None = None) -> None:
    """One panel per kernel: forward + backward time against the L2 relative error (the quantizer: code-flip
    rate) on ``scene`` (default CamVid when measured, else white noise), one marker per method, the Pareto
    frontier dashed, the legend below each panel. Zero errors are drawn on their own line a decade below the panel's
    smallest error, its tick labelled "exact (0)"."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator

    rows = [r for r in records if r.get("suite") == "accuracy" and r.get("fwd_bwd_ms") is not None]
    if not rows:
        raise ValueError("no accuracy records with times to plot (run --suite accuracy)")
    scene = scene or ("camvid" if any(r["scene"] == "camvid" for r in rows) else "white_noise")
    kernels = list(dict.fromkeys(r["kernel"] for r in rows))
    columns = min(4, len(kernels))
    figure, axes = plt.subplots(-(-len(kernels) // columns), columns, figsize=(4.2 * columns,
                                5.0 * -(-len(kernels) // columns)), squeeze=False)
    markers = "osD^vP*Xhp<>"
    for axis, kernel in zip(axes.flat, kernels):
        selected = [r for r in rows if r["kernel"] == kernel and r["scene"] == scene]
        metric = "code_flip_rate" if kernel == "quantize_ste" else "l2_rel_err"
        positive = [r[metric] for r in selected if r[metric] > 0]
        floor = min(positive) / 10 if positive else 1e-9  # where exact (zero-error) points are drawn
        points = []
        for index, row in enumerate(selected):
            error = max(row[metric], floor)
            points.append((row["fwd_bwd_ms"], error))
            axis.scatter(row["fwd_bwd_ms"], error, marker=markers[index % len(markers)], s=36,
                         color=plt.cm.tab20(index % 20), label=row["method"] + (" (exact)" if row[metric] == 0 else ""))
        frontier = pareto_frontier(points)
        axis.step([p[0] for p in frontier], [p[1] for p in frontier], where="post", color="0.4", linestyle="--",
                  linewidth=1, label="Pareto frontier")
        axis.set_xscale("log"), axis.set_yscale("log")
        if any(row[metric] == 0 for row in selected):  # exact points sit on their own labelled line, not at a value
            axis.axhline(floor, color="0.8", linewidth=0.8, zorder=0)
            ticks = [t for t in axis.get_yticks() if floor * 3 < t]
            axis.set_yticks([floor, *ticks], ["exact (0)", *[f"{t:.0e}" for t in ticks]])
            axis.set_ylim(floor / 2, max(p[1] for p in points) * 2)
        axis.set_title(kernel, fontsize=9)
        axis.set_xlabel("forward + backward (ms)" if not kernel.startswith("lens_") else
                        "PSF render + conv fwd+bwd (ms)", fontsize=8)
        axis.set_ylabel("code-flip rate" if metric == "code_flip_rate" else f"L2 relative error ({scene})", fontsize=8)
        # below the panel: a legend inside would hide points
        axis.legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2, frameon=False)
        axis.tick_params(labelsize=7)
        # ticks at 1, 2, 5 x 10^n, written plainly; the 2 and 5 labelled only on an axis shorter than two decades,
        # where they would not overlap (a log axis shorter than a decade would otherwise have no label)
        times = [p[0] for p in points]
        axis.xaxis.set_minor_locator(LogLocator(subs=(2, 5)))
        axis.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        short = max(times) / min(times) < 100
        axis.xaxis.set_minor_formatter(FuncFormatter(lambda value, _, short=short: f"{value:g}" if short else ""))
    for axis in list(axes.flat)[len(kernels):]:
        axis.axis("off")
    device = rows[0]["device"]
    figure.suptitle(f"error against run time ({device}, {rows[0]['threads']} torch threads)", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
