"""`warpsense bench`: every Warp kernel against its plain-torch reference (and alternative methods), forward and
backward, with error against a float64 reference: the error-against-run-time table of the design card.

Timing: median and IQR over repetitions after warm-up (compilation and cudnn tuning excluded), the device
synchronised around each repetition. "bwd" times the backward pass alone (the graph is built outside the timed
region). Errors: max abs and max relative (to the reference's max magnitude) against the same computation in float64.
"""

from __future__ import annotations

import platform
import time

import torch
import torch.nn.functional as F

from warpsense.bench import BENCH_SUITES
from warpsense.bench.timing import UNSTABLE_NOTE, _summary, _sync, is_unstable, time_function, time_latency
from warpsense.files import environment, write_json
from warpsense.ops import (
    cfa_mosaic,
    lovasz_softmax,
    poisson_gaussian,
    psf_conv,
    quantize_ste,
    softmax_cross_entropy,
    upsample_concat,
)
from warpsense.ops.psf import _conv2d_warp_gradient, psf_conv_fft, psf_conv_patch
from warpsense.ops.reference import (
    cfa_mosaic_reference,
    edge_aware_smoothness_reference,
    lovasz_softmax_reference,
    poisson_gaussian_reference,
    psf_conv_reference,
    quantize_reference,
    upsample_concat_reference,
)
from warpsense.ops.smoothness import edge_aware_smoothness


def time_backward(forward, inputs, device, repeats: int, warmup: int = 2) -> dict:
    """Backward pass alone: ``forward()`` builds the graph untimed, then autograd.grad is timed."""
    samples = []
    for index in range(warmup + repeats):
        out = forward()
        grad = torch.ones_like(out)
        _sync(device)
        start = time.perf_counter()
        torch.autograd.grad(out, inputs, grad)
        _sync(device)
        if index >= warmup:
            samples.append((time.perf_counter() - start) * 1e3)
    return _summary(samples)


def _errors(output: torch.Tensor, reference: torch.Tensor) -> dict:
    difference = (output.double() - reference.double()).abs().max().item()
    return {"max_abs_err": difference, "max_rel_err": difference / max(reference.abs().max().item(), 1e-30)}


def _metadata(device: str) -> dict:
    name = torch.cuda.get_device_name() if device == "cuda" else (platform.processor() or platform.machine())
    return {**environment(), "device_name": name, "cpu_count": torch.get_num_threads()}


class Bench:
    def __init__(self, device: str, repeats: int):
        self.device, self.repeats, self.records = device, repeats, []

    def record(self, kernel, method, dtype, shape, pass_name, timing, errors=None, bytes_moved=None, **extra):
        row = {"kernel": kernel, "method": method, "device": self.device, "dtype": dtype, "shape": list(shape),
               "pass": pass_name, "median_ms": timing["median_ms"], "iqr_ms": timing["iqr_ms"],
               "unstable": is_unstable(timing["median_ms"], timing["iqr_ms"]),
               "max_abs_err": (errors or {}).get("max_abs_err"), "max_rel_err": (errors or {}).get("max_rel_err")}
        if bytes_moved is not None:
            row["bandwidth_gb_s"] = bytes_moved / (timing["median_ms"] * 1e-3) / 1e9
        row.update(extra)
        self.records.append(row)
        if len(self.records) == 1:
            print(f"{'kernel':>16s} {'method':>12s} {'dtype':>13s} {'shape':>22s} {'pass':>7s} {'median ms':>10s} "
                  f"{'IQR ms':>9s} {'max rel err':>11s}", flush=True)
        error = f"{row['max_rel_err']:11.3g}" if row["max_rel_err"] is not None else f"{'-':>11s}"
        print(f"{kernel:>16s} {method:>12s} {dtype:>13s} {str(tuple(shape)):>22s} {pass_name:>7s} "
              f"{timing['median_ms']:10.3f} {timing['iqr_ms']:9.3f} {error}"
              + (f"  {UNSTABLE_NOTE}" if row["unstable"] else ""), flush=True)

    def case(self, kernel, method, shape, function, inputs64, bytes_fwd=None, bytes_bwd=None, precisions=("float32",),
             reference=None, compare=True):
        """Time ``function(*inputs)`` fwd and bwd in float32, and the bf16-input error. Errors are against
        ``reference(*inputs64)`` (default: ``function`` itself in float64); ``compare=False`` records none (random
        outputs)."""
        expected = (reference or function)(*inputs64).detach()
        for precision in precisions:
            if precision == "float32":
                inputs = [x.detach().float().requires_grad_(x.requires_grad) for x in inputs64]
            else:  # bf16 autocast: inputs rounded to bf16, the op computes in float32
                inputs = [x.detach().bfloat16().requires_grad_(x.requires_grad) for x in inputs64]
            with torch.autocast(self.device, dtype=torch.bfloat16, enabled=precision == "bf16_autocast"):
                with torch.no_grad():
                    errors = _errors(function(*inputs), expected) if compare else None
                    timing = time_function(lambda inputs=inputs: function(*inputs), self.device, self.repeats)
                self.record(kernel, method, precision, shape, "fwd", timing, errors, bytes_fwd)
                grads = [x for x in inputs if x.requires_grad]
                if grads and precision == "float32":
                    timing = time_backward(lambda inputs=inputs: function(*inputs), grads, self.device, self.repeats)
                    self.record(kernel, method, precision, shape, "bwd", timing, None, bytes_bwd)
                    # one autograd call: the host queues the backward while the forward runs, as in training
                    timing = time_function(
                        lambda inputs=inputs, grads=grads: torch.autograd.grad(function(*inputs).sum(), grads),
                        self.device, self.repeats)
                    self.record(kernel, method, precision, shape, "fwd+bwd", timing)


def run_bench(device: str = "cpu", quick: bool = False, json_out: str | None = None, plot_out: str | None = None,
              suite: str = "kernels", camvid_root: str | None = None, seeds: tuple[int, ...] = (0,),
              overrides: tuple[str, ...] = ()) -> list[dict]:
    """Run a benchmark suite ("kernels": every op against its reference; "accuracy": error against run time,
    `warpsense.bench.accuracy`, with CamVid frames from ``camvid_root`` when given; "train": training step and
    latency of the whole system against the plain-torch baseline, of the camvid_codesign preset changed by
    ``overrides``; "all"; "time-to-accuracy", for each of ``seeds``) and write the JSON / the accuracy plot."""
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device available")
    if suite not in BENCH_SUITES:
        raise ValueError(f"--suite must be one of {BENCH_SUITES}, got {suite!r}")
    if tuple(seeds) != (0,) and suite != "time-to-accuracy":
        raise ValueError(f"--seeds repeats the time-to-accuracy suite's training runs; the {suite!r} suite has none")
    if plot_out and suite not in ("accuracy", "all", "time-to-accuracy"):
        raise ValueError(f"--plot draws the accuracy suite's error against run time or the time-to-accuracy curves: "
                         f"use --suite accuracy, all or time-to-accuracy, not {suite!r}")
    if overrides and suite != "train":
        raise ValueError(f"--set configures the train suite's preset, not the {suite!r} suite")
    records, metadata = [], _metadata(device)
    if overrides:
        metadata["overrides"] = list(overrides)
    if suite in ("kernels", "all"):
        records += _kernel_suite(device, quick)
    if suite in ("accuracy", "all"):
        from warpsense.bench.accuracy import run_accuracy_suite

        records += run_accuracy_suite(device, quick, camvid_root)
    if suite in ("train", "all"):
        from warpsense.bench.train_suite import run_train_suite

        records += run_train_suite(device, quick, metadata, overrides)
    if suite == "time-to-accuracy":
        from warpsense.bench.time_to_accuracy import plot_time_to_accuracy, run_time_to_accuracy_suite

        records += run_time_to_accuracy_suite(device, quick, camvid_root, metadata, tuple(seeds))
        if plot_out:
            plot_time_to_accuracy(records, plot_out)
        plot_out = None
    unstable = [record for record in records if record.get("unstable")]
    if unstable:
        print(f"{len(unstable)} of {len(records)} rows UNSTABLE (their IQR exceeds their median; \"unstable\": true "
              "in the JSON): rerun them on an idle machine before quoting them", flush=True)
    if json_out:
        write_json(json_out, {"metadata": metadata, "records": records})
    if plot_out:
        from warpsense.bench.accuracy import plot_accuracy

        plot_accuracy(records, plot_out)
    return records


def _kernel_suite(device: str, quick: bool) -> list[dict]:
    torch.manual_seed(0)
    bench = Bench(device, repeats=5 if quick else 30)
    if quick:
        sizes = [(1, 96, 128)]
    elif device == "cuda":
        sizes = [(1, 192, 640), (16, 192, 640), (1, 360, 480), (16, 360, 480), (1, 1024, 2048)]
    else:
        sizes = [(1, 192, 640), (16, 192, 640), (1, 360, 480), (16, 360, 480)]
    precisions = ("float32", "bf16_autocast")
    for batch, height, width in sizes:
        pixels = batch * height * width
        rgb = torch.rand(batch, 3, height, width, dtype=torch.float64, device=device, requires_grad=True)
        phi = torch.rand(2, 2, 3, dtype=torch.float64, device=device, requires_grad=True)
        shape = (batch, 3, height, width)
        bench.case("cfa_mosaic", "warp", shape, cfa_mosaic, [rgb, phi], 16 * pixels, 28 * pixels, precisions)
        bench.case("cfa_mosaic", "torch_eager", shape, cfa_mosaic_reference, [rgb, phi], 16 * pixels, 28 * pixels)
        raw = torch.rand(batch, 1, height, width, dtype=torch.float64, device=device, requires_grad=True)
        raw_shape = (batch, 1, height, width)
        bench.case("poisson_gaussian", "warp", raw_shape, lambda r: poisson_gaussian(r, 0.015, 0.002, 3), [raw],
                   8 * pixels, 12 * pixels, precisions)
        bench.case("poisson_gaussian", "torch_eager", raw_shape,
                   lambda r: poisson_gaussian_reference(r, 0.015, 0.002, torch.randn_like(r)), [raw], 8 * pixels,
                   12 * pixels, compare=False)  # its own random draws: no pointwise reference
        bench.case("quantize_ste", "warp", raw_shape, lambda r: quantize_ste(r, 10), [raw], 8 * pixels, 12 * pixels,
                   precisions)
        bench.case("quantize_ste", "torch_eager", raw_shape, lambda r: quantize_reference(r, 10), [raw], 8 * pixels,
                   12 * pixels)
    # PSF convolution: invariant and 5x5-varying, K = 15 (quick: K = 7 on a small image)
    psf_sizes = [(1, 64, 96)] if quick else ([(16, 192, 640), (1, 360, 480)] if device == "cuda" else [(1, 192, 640)])
    size = 7 if quick else 15
    from warpsense.optics import Lens

    lens_grid = Lens.from_json("phone_80deg").psf_grid().to(device)
    start = (lens_grid.shape[-1] - size) // 2
    varying = lens_grid[..., start : start + size, start : start + size]
    varying = (varying / varying.sum(dim=(-2, -1), keepdim=True)).requires_grad_()
    invariant = varying[:, 2:3, 2:3].detach().clone().requires_grad_()
    for batch, height, width in psf_sizes:
        image = torch.rand(batch, 3, height, width, dtype=torch.float64, device=device, requires_grad=True)
        shape = (batch, 3, height, width)
        bench.case("psf_conv_invariant", "warp", shape, lambda x, p: psf_conv(x, p, "direct"), [image, invariant])
        bench.case("psf_conv_invariant", "auto", shape, psf_conv, [image, invariant])
        bench.case("psf_conv_invariant", "cudnn_warp_gradient", shape, _conv2d_warp_gradient, [image, invariant])
        bench.case("psf_conv_invariant", "cudnn_conv2d" if device == "cuda" else "torch_conv2d", shape,
                   lambda x, p: F.conv2d(F.pad(x, (size // 2,) * 4, mode="replicate"),
                                         p[:, 0, 0].flip(-1, -2).unsqueeze(1), groups=3), [image, invariant])
        bench.case("psf_conv_invariant", "torch_fft", shape, lambda x, p: psf_conv_fft(x, p[:, 0, 0]),
                   [image, invariant])
        bench.case("psf_conv_varying", "warp", shape, lambda x, p: psf_conv(x, p, "direct"), [image, varying])
        # the approximation's error is against the exact varying result, not its own float64 run
        bench.case("psf_conv_varying", "torch_patch", shape, psf_conv_patch, [image, varying],
                   reference=psf_conv_reference)
        bench.case("psf_conv_varying", "torch_blend", shape, psf_conv_reference, [image, varying])
    # the training loss's edge-aware smoothness: 11 class probabilities in the network's channels-last layout
    smooth_sizes = [(1, 96, 128)] if quick else ([(16, 352, 480)] if device == "cuda" else [(1, 192, 640)])
    for batch, height, width in smooth_sizes:
        probabilities = torch.softmax(torch.randn(batch, 11, height, width, dtype=torch.float64, device=device), 1)
        probabilities = probabilities.contiguous(memory_format=torch.channels_last).requires_grad_()
        guide = torch.rand(batch, height, width, dtype=torch.float64, device=device, requires_grad=True)
        shape = (batch, 11, height, width)
        bench.case("edge_smoothness", "warp", shape, edge_aware_smoothness, [probabilities, guide])
        bench.case("edge_smoothness", "torch_eager", shape, edge_aware_smoothness_reference, [probabilities, guide])
        # the loss's other terms at the same size: Lovasz from one sort, softmax with per-pixel cross-entropy
        labels = torch.randint(0, 11, (batch, height, width), device=device)
        bench.case("lovasz_softmax", "warp", shape, lambda p, t=labels: lovasz_softmax(p, t), [probabilities])
        bench.case("lovasz_softmax", "torch_eager", shape, lambda p, t=labels: lovasz_softmax_reference(p, t),
                   [probabilities])
        logits = torch.randn(batch, 11, height, width, dtype=torch.float64, device=device)
        logits = logits.contiguous(memory_format=torch.channels_last).requires_grad_()
        bench.case("softmax_cross_entropy", "warp", shape,
                   lambda z, t=labels: torch.cat([out.flatten() for out in softmax_cross_entropy(z, t)]), [logits])
        bench.case("softmax_cross_entropy", "torch_eager", shape,
                   lambda z, t=labels: torch.cat([F.cross_entropy(z, t, reduction="none").flatten(),
                                        torch.softmax(z, dim=1).flatten()]), [logits])
    # the decoder's upsampling + skip concatenation, channels-last: DSUNet's join into full resolution (width 24)
    up_sizes = [(1, 48, 48, 64)] if quick else ([(16, 48, 176, 240)] if device == "cuda" else [(1, 48, 96, 160)])
    for batch, channels, height, width in up_sizes:
        low = torch.rand(batch, channels, height, width, dtype=torch.float64, device=device)
        low = low.contiguous(memory_format=torch.channels_last).requires_grad_()
        skip = torch.rand(batch, channels // 2, 2 * height, 2 * width, dtype=torch.float64, device=device)
        skip = skip.contiguous(memory_format=torch.channels_last).requires_grad_()
        shape = (batch, channels, height, width)
        bench.case("upsample_concat", "warp", shape, upsample_concat, [low, skip], precisions=precisions)
        bench.case("upsample_concat", "torch_eager", shape, upsample_concat_reference, [low, skip],
                   precisions=precisions)
    if not quick:
        _end_to_end(bench, device)
    return bench.records


def _end_to_end(bench: Bench, device: str) -> None:
    """Sensor simulation + the 0.18M DSUNet at 192x640 batch 1: warpsense ops vs the same pipeline written with the
    plain-torch reference ops; eager, and replayed as a CUDA graph on CUDA."""
    from warpsense.camera import Camera
    from warpsense.config import load_config
    from warpsense.models import build_model

    config = load_config(None, ["exposure.learnable=false", "cfa.mode=fixed"])
    camera = Camera.from_config(config).to(device).eval()
    network = build_model("dsunet", in_channels=1, num_classes=19, width=16, channels_last=True).to(device).eval()
    radiance = torch.rand(1, 3, 192, 640, device=device)
    phi = camera.responses()

    def baseline():
        raw = cfa_mosaic_reference(radiance, phi)
        raw = poisson_gaussian_reference(raw, 0.015, 0.002, torch.randn_like(raw))
        return network(quantize_reference(raw, 10))

    def ours():
        return network(camera(radiance))

    with torch.no_grad(), torch.autocast(device, dtype=torch.bfloat16, enabled=device == "cuda"):
        for name, function in (("torch_eager_sensor", baseline), ("warp_sensor", ours)):
            bench.record("sensor_plus_network", name, "bf16" if device == "cuda" else "float32", (1, 3, 192, 640),
                         "fwd", time_latency(function, device))
            if device == "cuda":
                bench.record("sensor_plus_network", name + "_graph", "bf16", (1, 3, 192, 640), "fwd",
                             time_latency(function, device, graph=True))
        sensed = camera(radiance)
        bench.record("network_only", "dsunet", "bf16" if device == "cuda" else "float32", (1, 1, 192, 640), "fwd",
                     time_latency(lambda: network(sensed), device))
