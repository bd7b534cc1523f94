"""Batch-1 latency of the whole system (uint8 frame -> logits), warpsense against the plain-torch baseline, in one run.

    python tools/bench_latency.py [--device cuda] [--size 192x640] [--repeats 300] [--json OUT] [--profile DIR]

The train suite's latency records (`warpsense.bench.train_suite.latency`: the baseline's Gaussian camera, the same
camera in warpsense, the codesign camera; DSUNet width 16, bf16 on CUDA), eager and (CUDA) replayed as a CUDA graph,
without the suite's training runs. Medians of synchronised wall-clock ms; the eager calls of the three systems are
interleaved (`time_interleaved`), ``--repeats`` rounds. ``--profile DIR`` also writes each
system's kernels by GPU time over 20 eager calls (`torch.profiler`) to DIR/latency_<method>_<camera>.txt.
"""

from __future__ import annotations

import argparse
import os

import torch

from warpsense.bench.timing import time_interleaved, write_kernel_table
from warpsense.bench.train_suite import inference, latency
from warpsense.files import write_json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--size", default="192x640", help="HxW of the frame")
    parser.add_argument("--repeats", type=int, default=300, help="eager calls of each system (interleaved)")
    parser.add_argument("--json", metavar="OUT")
    parser.add_argument("--profile", metavar="DIR", help="write each system's kernels by GPU time there (CUDA)")
    args = parser.parse_args()
    height, width = (int(part) for part in args.size.lower().split("x"))
    systems = (("torch_baseline", "simple"), ("warpsense", "simple"), ("warpsense", "codesign"))
    records = []

    def record(method, camera, mode, timing):
        records.append({"method": method, "camera": camera, "mode": mode, "shape": [1, 3, height, width], **timing})
        print(f"{method:>15s} {camera:>9s} {mode:>11s} {timing['median_ms']:8.3f} ms [IQR {timing['iqr_ms']:.3f}]",
              flush=True)

    # eager: the systems called in turn, so that the host's drift falls on each alike
    calls = {system: inference(*system, args.device, height, width) for system in systems}
    for (method, camera), timing in time_interleaved(calls, args.device, args.repeats).items():
        record(method, camera, "eager", timing)
    for method, camera in systems:
        if args.device == "cuda":
            record(method, camera, "graph", latency(method, camera, args.device, height, width, True))
        if args.profile and args.device == "cuda":
            os.makedirs(args.profile, exist_ok=True)
            infer = inference(method, camera, args.device, height, width)
            write_kernel_table(lambda infer=infer: [infer() for _ in range(20)], args.device,
                               os.path.join(args.profile, f"latency_{method}_{camera}.txt"), warmup=1, rows=40)
    if args.json:
        name = torch.cuda.get_device_name() if args.device == "cuda" else "cpu"
        write_json(args.json, {"device": name, "records": records})


if __name__ == "__main__":
    main()
