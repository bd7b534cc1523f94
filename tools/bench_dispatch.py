"""Host time of the camera's Warp ops per call: through their torch.library custom op, as called (`WarpOp`) and
through the function the op wraps.

    python tools/bench_dispatch.py [--device cuda] [--size 192x640] [--calls 300]

Round 27's cProfile of batch-1 eager inference on an H100 (torch 2.11, `tools/bench_latency.py --host-profile`)
gave torch's custom-op wrapper (`torch/_library/custom_ops.py`, ``backend_impl``) 0.3-0.4 ms of its own time per
call of `sensor_capture` and `psf_conv`, where published measurements of the custom-op dispatch put it at ~7-16 us.
This tool measures it without a profiler: for each op, the host time of ``--calls`` calls (no synchronisation
between them, so the GPU's work overlaps) through the custom op (``.op``), through the `WarpOp` the package calls
(which skips the dispatcher where nothing needs it: no gradient) and through the wrapped function
(``.function``), with gradients off and on, and a trivial custom op (a clone) for the dispatch alone.
"""

from __future__ import annotations

import argparse
import time

import torch

from warpsense.bench import parse_size
from warpsense.ops import psf, sensor
from warpsense.ops._warp import WarpOp


@torch.library.custom_op("warpsense_bench::clone", mutates_args=())
def _clone(x: torch.Tensor) -> torch.Tensor:
    return x.clone()


_clone.register_fake(lambda x: torch.empty_like(x))


def host_us(function, device: str, calls: int) -> float:
    """Host microseconds per call of ``function()`` over ``calls`` calls after 20 untimed."""
    for _ in range(20):
        function()
    if device == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(calls):
        function()
    elapsed = (time.perf_counter() - start) / calls * 1e6
    if device == "cuda":
        torch.cuda.synchronize()
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--size", default="192x640", help="HxW of the one image")
    parser.add_argument("--calls", type=int, default=300)
    args = parser.parse_args()
    try:
        height, width = parse_size(args.size, "--size", "192x640")
    except ValueError as error:
        parser.error(str(error))
    device = args.device
    rgb = torch.rand(1, 3, height, width, device=device)
    level = torch.full((1,), 0.01, device=device)
    sensor_inputs = (rgb, torch.rand(2, 2, 3, device=device), level, level.clone(), torch.ones(1, device=device),
                     torch.zeros(1, dtype=torch.int32, device=device), 0, 1, 1023)
    cells = psf.node_cells(torch.rand(3, 5, 5, 15, 15, device=device) / 225)
    small = torch.rand(16, device=device)
    cases = {"clone": (_clone, (small,)), "sensor_capture": (sensor._sensor_capture, sensor_inputs),
             "psf_conv": (psf._psf_conv_cells, (rgb, cells, 5, 5))}
    for grad in (False, True):
        with torch.set_grad_enabled(grad):
            for name, (op, inputs) in cases.items():
                custom, function = (op.op, op.function) if isinstance(op, WarpOp) else (op, op._init_fn)
                through_op = host_us(lambda op=custom, inputs=inputs: op(*inputs), device, args.calls)
                called = host_us(lambda op=op, inputs=inputs: op(*inputs), device, args.calls)
                direct = host_us(lambda op=function, inputs=inputs: op(*inputs), device, args.calls)
                print(f"grad {'on ' if grad else 'off'} {name:>15s}: custom op {through_op:8.1f} us, as called "
                      f"{called:8.1f} us, direct {direct:8.1f} us, dispatch {through_op - direct:+8.1f} us",
                      flush=True)


if __name__ == "__main__":
    main()
