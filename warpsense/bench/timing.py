"""Timing helpers: median and IQR after warm-up, with the device synchronised around each repetition; the inference
latency every benchmark and `warpsense eval --latency` report (`time_latency`)."""

from __future__ import annotations

import statistics
import time

import torch


def _sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def _summary(samples_ms: list[float]) -> dict:
    quartiles = statistics.quantiles(samples_ms, n=4) if len(samples_ms) > 1 else [samples_ms[0]] * 3
    median, iqr = statistics.median(samples_ms), quartiles[2] - quartiles[0]
    return {"median_ms": median, "iqr_ms": iqr, "repeats": len(samples_ms), "unstable": is_unstable(median, iqr)}


def is_unstable(median_ms: float, iqr_ms: float) -> bool:
    """Whether a timing's spread (its IQR) exceeds its median: the calls were not measuring the code alone (another
    job on the cores, OpenMP threads waiting on each other, frequency changes), and the median is not a result."""
    return iqr_ms > median_ms


UNSTABLE_NOTE = "UNSTABLE: IQR > median, not a result (a busy machine?)"
"""What a benchmark prints beside a row `is_unstable` flags."""


def time_function(function, device, repeats: int = 20, warmup: int = 3) -> dict:
    """Wall time of ``function()`` per call (ms); warm-up calls (compilation, cudnn tuning) are excluded."""
    for _ in range(warmup):
        function()
    _sync(device)
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        _sync(device)
        samples.append((time.perf_counter() - start) * 1e3)
    return _summary(samples)


def time_cuda_graph(function, repeats: int = 50, warmup: int = 3) -> dict:
    """Capture ``function()`` in a CUDA graph (after warm-up on a side stream) and time its replay."""
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        for _ in range(warmup):
            function()
    torch.cuda.current_stream().wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        function()
    return time_function(graph.replay, "cuda", repeats, warmup=2)


LATENCY_REPEATS = 50
"""Timed calls of an eager inference (`time_latency`)."""

GRAPH_LATENCY_REPEATS = 100
"""Timed replays of an inference captured as a CUDA graph (`time_latency`)."""


def time_latency(function, device, graph: bool = False, repeats: int | None = None) -> dict:
    """Latency of one inference ``function()`` (a batch through a model, no arguments), as `time_function`'s
    summary: eager, or captured once and replayed as a CUDA graph (``graph``, CUDA only: no host work per call).

    Args:
        function: the inference; the caller enters what it runs under (`torch.no_grad`, autocast, a cached camera)
            inside it or around this call.
        device: where it runs (synchronised around each call).
        graph: replay a CUDA graph instead of calling eagerly.
        repeats: timed calls (default: `LATENCY_REPEATS` eager, `GRAPH_LATENCY_REPEATS` replayed).
    """
    if graph:
        return time_cuda_graph(function, GRAPH_LATENCY_REPEATS if repeats is None else repeats)
    return time_function(function, device, LATENCY_REPEATS if repeats is None else repeats)


def model_latency(model, device, height: int, width: int, batch: int, repeats: int = LATENCY_REPEATS) -> dict:
    """Median latency (ms, `time_latency`) of a loaded `SensingModel` on random uint8 frames: sensor simulation +
    network, and the network alone; on CUDA also replayed as CUDA graphs.

    The checkpoint's camera is fixed, so it runs cached (`Camera.cached`), as a deployed one would.

    Args:
        model: the model, on ``device``.
        device: a torch.device.
        height, width, batch: the frames' size.
        repeats: timed calls of each, eager and replayed.

    Returns:
        {"device", "height", "width", "batch", "camera_cached", "sensor_plus_network_ms", "network_ms"}, with
        "sensor_plus_network_graph_ms" and "network_graph_ms" on CUDA: `warpsense eval --latency`'s record.
    """
    from warpsense.camera.camera import cached_cameras  # the camera loads Warp: only when a model is timed

    images = torch.randint(0, 256, (batch, 3, height, width), dtype=torch.uint8, device=device)
    sensed = model.sense(images)
    result = {"device": str(device), "height": height, "width": width, "batch": batch, "camera_cached": True}
    with torch.no_grad(), cached_cameras(model):
        result["sensor_plus_network_ms"] = time_latency(lambda: model(images), device, repeats=repeats)["median_ms"]
        result["network_ms"] = time_latency(lambda: model.network(sensed), device, repeats=repeats)["median_ms"]
        if device.type == "cuda":
            result["sensor_plus_network_graph_ms"] = time_latency(lambda: model(images), device, graph=True,
                                                                  repeats=repeats)["median_ms"]
            result["network_graph_ms"] = time_latency(lambda: model.network(sensed), device, graph=True,
                                                      repeats=repeats)["median_ms"]
    return result


LATENCY_ROWS = (("sensor + network", "sensor_plus_network_ms"), ("network alone", "network_ms"),
                ("sensor + network, CUDA graph", "sensor_plus_network_graph_ms"),
                ("network alone, CUDA graph", "network_graph_ms"))
"""The figures of a `model_latency` record, in the order `latency_lines` prints them, with their row names."""


def latency_lines(record: dict) -> list[str]:
    """`model_latency`'s record as a small table: a head naming the input and device, then one row per figure it
    holds (median ms and frames per second), the CUDA-graph rows only where it has them."""
    frames = record["batch"]
    lines = [f"latency: batch {frames} of {record['height']}x{record['width']} (HxW) on {record['device']}, "
             f"median per batch{', camera cached' if record.get('camera_cached') else ''}"]
    rows = [(name, record[key]) for name, key in LATENCY_ROWS if record.get(key) is not None]
    width = max(len(name) for name, _ in rows)
    lines += [f"  {name:<{width}s}  {ms:9.3f} ms  {1000 * frames / ms:9.1f} frames/s" if ms > 0 else
              f"  {name:<{width}s}  {ms:9.3f} ms" for name, ms in rows]
    return lines

