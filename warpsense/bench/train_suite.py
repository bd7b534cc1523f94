"""`warpsense bench --suite train`: the training step and batch-1 latency of the whole system (sensor + network),
warpsense against the plain-torch baseline (docs/references.md, convention 5) built from `warpsense.ops.reference`
and the same network and loss run through torch's own ops (`method_ops`: none of warpsense's Warp network or loss
ops), in one run.

Cameras: "simple" = the baseline's camera (one 7x7 Gaussian PSF, exposure, 2x2 softmax CFA, Poisson-Gaussian
noise, 10-bit ADC); "codesign" = the camvid_codesign preset's camera (learnable 80/68 deg lens rendered every step,
5x5 PSF grid, the rest learnable as in training). Losses: "ce" (cross-entropy) and "full" (0.6 OHEM + 0.4 Lovasz +
0.01 edge-aware smoothness, the training loss). Network: the camvid presets' (`configs/presets/camvid.toml`'s
[model], the network the recipe trains; ``--set`` changes it, e.g. model.squeeze=true) on the RAW mosaic, in bf16
autocast on CUDA.
"""

from __future__ import annotations

import contextlib
import time

import torch
from torch import nn

from warpsense.bench.timing import UNSTABLE_NOTE, _sync, is_unstable, time_cuda_graph, time_function, time_latency
from warpsense.camera import Camera
from warpsense.camera.camera import cached_cameras, set_finite_check
from warpsense.config import load_config
from warpsense.data.color import srgb_to_linear
from warpsense.errors import first_line
from warpsense.models import network_from_config
from warpsense.models.dsunet import torch_ops
from warpsense.ops import psf_conv
from warpsense.ops.reference import (
    cfa_mosaic_reference,
    poisson_gaussian_reference,
    psf_conv_reference,
    quantize_reference,
)
from warpsense.system import SensingModel
from warpsense.train.losses import LOSS_OPS
from warpsense.train.step import TrainingStep

PRESET = "camvid_codesign"
"""The preset whose network (and codesign camera) the suite times: the recipe's."""


def gaussian_psf(size: int = 7, sigma: float = 1.2, channels: int = 3) -> torch.Tensor:
    """[C, 1, 1, K, K] isotropic Gaussian PSF summing to 1."""
    x = torch.arange(size, dtype=torch.float32) - size // 2
    kernel = torch.exp(-0.5 * (x[:, None] ** 2 + x[None, :] ** 2) / sigma**2)
    return (kernel / kernel.sum()).expand(channels, 1, 1, size, size).contiguous()


class BaselineCamera(nn.Module):
    """The plain-torch camera a user would write: eager reference ops (conv2d blur, mosaic, noise, STE)."""

    def __init__(self):
        super().__init__()
        self.register_buffer("psf", gaussian_psf())
        self.gain_logit = nn.Parameter(torch.tensor(-1.3863))
        self.logits = nn.Parameter(torch.nn.functional.one_hot(torch.tensor([[0, 1], [1, 2]]), 3).float() * 4)

    def forward(self, radiance, image_index=None):
        image = psf_conv_reference(radiance, self.psf)
        phi = torch.softmax(self.logits, dim=-1) * (0.25 + 3.75 * torch.sigmoid(self.gain_logit))
        raw = cfa_mosaic_reference(image, phi)
        raw = poisson_gaussian_reference(raw, 0.015, 0.002, torch.randn_like(raw))
        return quantize_reference(raw, 10)


class SimpleCamera(nn.Module):
    """The same camera in warpsense: psf_conv (auto method) then the fused sensor kernel."""

    def __init__(self):
        super().__init__()
        self.register_buffer("psf", gaussian_psf())
        self.camera = Camera.from_config(load_config(None, ["cfa.mode=softmax"]))

    def forward(self, radiance, image_index=None):
        return self.camera(psf_conv(radiance, self.psf), image_index)


def build(method: str, camera_name: str, device, channels_last: bool = True,
          overrides: tuple[str, ...] = ()) -> tuple[nn.Module, nn.Module]:
    """The camera and network a case times: the network of the `PRESET` changed by ``overrides`` (both methods),
    with the preset's codesign camera or the baseline's simple camera."""
    if camera_name == "codesign":
        if method != "warpsense":
            raise ValueError("the codesign camera is timed for warpsense only")
        camera = Camera.from_config(load_config(PRESET, list(overrides)))
    else:
        camera = BaselineCamera() if method == "torch_baseline" else SimpleCamera()
    return camera.to(device), recipe_network(channels_last, overrides).to(device)


def recipe_network(channels_last: bool = True, overrides: tuple[str, ...] = ()) -> nn.Module:
    """The `PRESET`'s network (changed by ``overrides``) for the RAW mosaic (1 channel, 2 x 2 tile, CamVid's 11
    classes), in the layout ``channels_last`` asks for: the suite times the network the recipe trains."""
    model = load_config(PRESET, [*overrides, f"model.channels_last={str(channels_last).lower()}"]).model
    return network_from_config(model, 1, 11, 2)


@contextlib.contextmanager
def method_ops(method: str):
    """The context a method's network and loss run in: torch's own ops for the plain-torch baseline (the network's
    through `dsunet.torch_ops`, the loss's plain-torch references through `LOSS_OPS`), warpsense's fused Warp ops
    for warpsense."""
    if method != "torch_baseline":
        yield
        return
    with torch_ops(), LOSS_OPS.torch_ops():
        yield


def training_throughput(method, camera_name, loss_name, device, batch, height, width, steps, warmup,
                        compile_mode: str = "off", cuda_graph: bool = False, overrides: tuple[str, ...] = ()) -> float:
    """Images per second of full training steps (the training engine's `TrainingStep`: sensor + network forward,
    loss, backward, fused AdamW on CUDA), after ``warmup`` steps (which include any compilation)."""
    torch.manual_seed(0)
    # eager steps run the network in NHWC (bf16's fast kernels); inductor does better from NCHW (its own layouts)
    system = SensingModel(*build(method, camera_name, device, compile_mode == "off", overrides)).train()
    set_finite_check(system, False)  # as in training: no host read per step
    parameters = [p for p in system.parameters() if p.requires_grad]
    cuda = torch.device(device).type == "cuda"
    optimizer = torch.optim.AdamW(parameters, lr=1e-3, fused=cuda)
    loss_config = load_config(None, [] if loss_name == "full" else
                              ["loss.ohem_fraction=1.0", "loss.lovasz_weight=0.0", "loss.smooth_weight=0.0"]).loss
    torch._dynamo.reset()
    step = TrainingStep(loss_config, optimizer, [], steps + warmup, amp=cuda, compile_mode=compile_mode,
                        cuda_graph=cuda_graph)
    with method_ops(method):
        return step_throughput(step, system, batch, height, width, steps, warmup, device)


def step_throughput(step: TrainingStep, model, batch: int, height: int, width: int, steps: int, warmup: int,
                    device) -> float:
    """Images per second of joint-phase ``step``s of ``model`` on random uint8 frames [batch, 3, height, width]
    and 11-class labels, timed over ``steps`` after ``warmup`` steps (where compilation and graph capture
    happen)."""
    images = torch.randint(0, 256, (batch, 3, height, width), dtype=torch.uint8, device=device)
    labels = torch.randint(0, 11, (batch, height, width), device=device)
    for index in range(warmup):
        step(model, images, labels, index, joint=True)
    _sync(device)
    start = time.perf_counter()
    for index in range(steps):
        step(model, images, labels, warmup + index, joint=True)
    _sync(device)
    return steps * batch / (time.perf_counter() - start)


def inference(method, camera_name, device, height, width, cached: contextlib.ExitStack | None = None,
              overrides: tuple[str, ...] = ()):
    """A batch-1 end-to-end inference (uint8 frame -> logits) of the system, as a function of no arguments: the
    camera and network in eval mode, bf16 autocast on CUDA. ``cached``: an exit stack that the camera's
    `Camera.cached` context is entered on (the camera reuses its sensor arguments until the stack closes)."""
    torch.manual_seed(0)
    camera, network = build(method, camera_name, device, overrides=overrides)
    camera.eval(), network.eval()
    if cached is not None:
        cached.enter_context(cached_cameras(camera))
    frame = torch.randint(0, 256, (1, 3, height, width), dtype=torch.uint8, device=device)
    amp = torch.device(device).type == "cuda"

    def infer():
        with method_ops(method), torch.no_grad(), torch.autocast(torch.device(device).type, dtype=torch.bfloat16,
                                                                   enabled=amp):
            return network(camera(srgb_to_linear(frame)))

    return infer


def latency(method, camera_name, device, height, width, graph: bool, cached: bool = False,
            overrides: tuple[str, ...] = ()) -> dict:
    """Batch-1 end-to-end inference time (`inference`), eager or replayed as a CUDA graph; ``cached``: eager with
    the camera cached (`Camera.cached`, a fixed camera's inference)."""
    with contextlib.ExitStack() as stack:
        infer = inference(method, camera_name, device, height, width, stack if cached else None, overrides)
        return time_latency(infer, device, graph)


def camera_pass(method, camera_name, device, batch, height, width, graph: bool,
                overrides: tuple[str, ...] = ()) -> dict:
    """The camera alone in training: forward from linear radiance [batch, 3, height, width] to RAW, and backward to
    its learnable parameters (the lens re-rendered, as in the joint phase), eager or replayed as a CUDA graph."""
    torch.manual_seed(0)
    camera, _ = build(method, camera_name, device, overrides=overrides)
    camera.train()
    set_finite_check(camera, False)
    parameters = [p for p in camera.parameters() if p.requires_grad]
    radiance = torch.rand(batch, 3, height, width, device=device) * 0.5
    weights = torch.randn(batch, 1, height, width, device=device)

    def step():
        raw = camera(radiance)
        return torch.autograd.grad((raw * weights).sum(), parameters)

    return time_cuda_graph(step, 50) if graph else time_function(step, device, 20)


def run_train_suite(device: str, quick: bool, metadata: dict, overrides: tuple[str, ...] = ()) -> list[dict]:
    """All records of the suite, of the `PRESET` changed by ``overrides`` (e.g. ``("model.squeeze=true",)``);
    prints one line each."""
    if quick:
        batch, height, width, steps, warmup = 2, 64, 96, 2, 1
    else:
        batch, height, width, steps, warmup = 16, 192, 640, 30, 5
    records = []

    def add(record):
        record.update({"suite": "train", "device": device, "device_name": metadata.get("device_name")})
        records.append(record)
        if len(records) == 1:
            print(f"train-suite {'method':>15s} {'camera':>9s} {'loss':>6s} {'compile':>8s} {'graph':>5s} "
                  "img/s or median ms [IQR ms]", flush=True)
        if "median_ms" in record:
            record["unstable"] = is_unstable(record["median_ms"], record["iqr_ms"])
        figure = (f"{record['images_per_s']:8.1f} img/s" if "images_per_s" in record
                  else f"{record['median_ms']:8.3f} ms [{record['iqr_ms']:.3f}]" if "median_ms" in record
                  else f"failed: {record['error']}")
        figure += f"  {UNSTABLE_NOTE}" if record.get("unstable") else ""
        kind = record.get("loss", record.get("mode"))
        print(f"train-suite {record['method']:>15s} {record['camera']:>9s} {kind:>6s}"
              f" {record.get('compile', ''):>8s} {'graph' if record.get('cuda_graph') else '':>5s} {figure}",
              flush=True)

    cases = [("torch_baseline", "simple"), ("warpsense", "simple"), ("warpsense", "codesign")]
    # (loss, torch.compile mode, whole-step CUDA graph); compiling on a CPU takes minutes of C++ compilation and
    # graphs need CUDA: both are timed on CUDA only, with the full loss
    runs = [("ce", "off", False), ("full", "off", False)]
    if device == "cuda":
        runs += [("full", "off", True), ("full", "default", True)]
    for method, camera_name in cases:
        for loss_name, compile_mode, cuda_graph in runs:
            record = {"method": method, "camera": camera_name, "loss": loss_name, "compile": compile_mode,
                      "cuda_graph": cuda_graph, "shape": [batch, 3, height, width]}
            extra_warmup = 5 if compile_mode != "off" or cuda_graph else 0  # compilation or capture
            try:
                record["images_per_s"] = training_throughput(method, camera_name, loss_name, device, batch, height,
                                                             width, steps, warmup + extra_warmup, compile_mode,
                                                             cuda_graph, overrides)
            except Exception as error:  # a compiler failure is a result to report, not the end of the suite
                if compile_mode == "off" and not cuda_graph:
                    raise
                record["error"] = f"{type(error).__name__}: {first_line(error)[:300]}"
            add(record)
    camera_shape = (2, 64, 96) if quick else (16, 352, 480)  # the CamVid recipe's training crop
    for method, camera_name in cases:
        for graph in ((False, True) if device == "cuda" else (False,)):
            timing = camera_pass(method, camera_name, device, *camera_shape, graph, overrides)
            add({"method": method, "camera": camera_name, "mode": "camera fwd+bwd " + ("graph" if graph else "eager"),
                 "median_ms": timing["median_ms"], "iqr_ms": timing["iqr_ms"], "shape": [camera_shape[0], 3,
                                                                                          *camera_shape[1:]]})
    for method, camera_name in cases:
        modes = ["eager", *(["eager_cached"] if method == "warpsense" else []),
                 *(["graph"] if device == "cuda" else [])]
        for mode in modes:
            timing = latency(method, camera_name, device, height, width, mode == "graph", mode == "eager_cached",
                             overrides)
            add({"method": method, "camera": camera_name, "mode": mode,
                 "median_ms": timing["median_ms"], "iqr_ms": timing["iqr_ms"], "shape": [1, 3, height, width]})
    return records
