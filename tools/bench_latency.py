"""Batch-1 latency of the whole system (uint8 frame -> logits), warpsense against the plain-torch baseline, in one run.

    python tools/bench_latency.py [--device cuda] [--size 192x640] [--repeats 300] [--json OUT] [--profile DIR]
        [--host-profile DIR]

The train suite's latency records (`warpsense.bench.train_suite.latency`: the baseline's Gaussian camera, the same
camera in warpsense, the codesign camera; DSUNet width 16, bf16 on CUDA), eager, warpsense's eager with the camera
cached (`Camera.cached`, mode "eager_cached") and (CUDA) replayed as a CUDA graph, without the suite's training runs.
Medians of synchronised wall-clock ms; the eager calls of all systems are interleaved (`time_interleaved`),
``--repeats`` rounds, each compared with the baseline's call of the same round (median difference and its 95%
interval). ``--profile DIR`` also writes each system's kernels by GPU time over 20 eager calls
(`torch.profiler`) to DIR/latency_<method>_<camera>.txt; ``--host-profile DIR`` each system's Python functions by
host time over 100 eager calls (cProfile) to DIR/host_<method>_<camera>.txt.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import os
import pstats

import torch

from warpsense.bench import parse_size
from warpsense.bench.timing import time_interleaved, write_kernel_table
from warpsense.bench.train_suite import inference, latency
from warpsense.files import write_json


def write_host_profile(function, path: str, calls: int = 100, rows: int = 45) -> None:
    """``calls`` calls of ``function`` under cProfile (after 3 untimed), the functions by their own time."""
    for _ in range(3):
        function()
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(calls):
        function()
    profiler.disable()
    with open(path, "w") as stream:
        stream.write(f"{calls} calls; times are totals over them\n")
        pstats.Stats(profiler, stream=stream).sort_stats("tottime").print_stats(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--size", default="192x640", help="HxW of the frame")
    parser.add_argument("--repeats", type=int, default=300, help="eager calls of each system (interleaved)")
    parser.add_argument("--json", metavar="OUT")
    parser.add_argument("--profile", metavar="DIR", help="write each system's kernels by GPU time there (CUDA)")
    parser.add_argument("--host-profile", metavar="DIR",
                        help="write each system's Python functions by host time over 100 eager calls there (cProfile)")
    args = parser.parse_args()
    try:
        height, width = parse_size(args.size, "--size", "192x640")
    except ValueError as error:
        parser.error(str(error))
    systems = (("torch_baseline", "simple"), ("warpsense", "simple"), ("warpsense", "codesign"))
    records = []

    def record(method, camera, mode, timing):
        records.append({"method": method, "camera": camera, "mode": mode, "shape": [1, 3, height, width], **timing})
        paired = (f"  vs the baseline, paired by round: {timing['vs_reference_ms']:+.3f} ms "
                  f"[{timing['vs_reference_ci95_ms'][0]:+.3f}, {timing['vs_reference_ci95_ms'][1]:+.3f}]"
                  if "vs_reference_ms" in timing else "")
        print(f"{method:>15s} {camera:>9s} {mode:>14s} {timing['median_ms']:8.3f} ms [IQR {timing['iqr_ms']:.3f}]"
              f"{paired}", flush=True)

    # eager: the systems called in turn, so that the host's drift falls on each alike; warpsense's systems also
    # with the camera cached (`Camera.cached`: a fixed camera's sensor arguments computed once)
    with contextlib.ExitStack() as stack:
        calls = {(*system, "eager"): inference(*system, args.device, height, width) for system in systems}
        calls.update({(*system, "eager_cached"): inference(*system, args.device, height, width, cached=stack)
                      for system in systems if system[0] == "warpsense"})
        reference = ("torch_baseline", "simple", "eager")
        for (method, camera, mode), timing in time_interleaved(calls, args.device, args.repeats,
                                                               reference=reference).items():
            record(method, camera, mode, timing)
    for method, camera in systems:
        if args.device == "cuda":
            record(method, camera, "graph", latency(method, camera, args.device, height, width, True))
        if args.profile and args.device == "cuda":
            os.makedirs(args.profile, exist_ok=True)
            infer = inference(method, camera, args.device, height, width)
            write_kernel_table(lambda infer=infer: [infer() for _ in range(20)], args.device,
                               os.path.join(args.profile, f"latency_{method}_{camera}.txt"), warmup=1, rows=40)
    if args.host_profile:
        os.makedirs(args.host_profile, exist_ok=True)
        for method, camera in systems:
            infer = inference(method, camera, args.device, height, width)
            write_host_profile(infer, os.path.join(args.host_profile, f"host_{method}_{camera}.txt"))
    if args.json:
        name = torch.cuda.get_device_name() if args.device == "cuda" else "cpu"
        write_json(args.json, {"device": name, "records": records})


if __name__ == "__main__":
    main()
