"""The PSF convolution's kernels at the camera's training shape, with their layout constants changed.

    python docs/records/psf/variants.py [--rows 4,8,16] [--taps 8,16] [--json OUT.json] [--against REFERENCE.pt]

Each variant runs in a process of its own (the kernels take ROWS and TAPS when their module is built): the
forward alone and the forward + gradient to the PSF grid (as the camera trains it), 16 x 3 x 352 x 480, 5 x 5 grid,
K = 15, float32, replayed as one CUDA graph (`warpsense.bench.timing.time_cuda_graph`, median of 50), and the
forward's and PSF gradient's largest relative difference from the shipped layout's (ROWS 8, TAPS 8).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

SHAPE, GRID, SIZE = (16, 3, 352, 480), (5, 5), 15


def measure(rows: int, taps: int, reference: str | None, blocks: tuple[int, int] | None = None) -> dict:
    import torch

    from warpsense.bench.timing import time_cuda_graph
    from warpsense.kernels import psf as kernels

    kernels.ROWS, kernels.TAPS = rows, taps  # before the kernels' modules are built
    from warpsense.ops import psf as psf_module
    from warpsense.ops import psf_conv

    if blocks:  # threads per block of the forward (and image adjoint) and of the PSF adjoint[, the forward's
        # minimum blocks a multiprocessor: its launch bounds, which cap its registers]
        psf_module.FORWARD_BLOCK, psf_module.CELLS_BLOCK = blocks[:2]
        # the forward's launch bounds must admit its block: the given minimum blocks, or none
        kernels.FORWARD_BOUNDS = (blocks[0], blocks[2]) if len(blocks) > 2 and blocks[2] else None
        # a fifth figure: the threads the PSF adjoint's launch aims for (ops.psf._THREADS_TARGET), as a power of
        # two (a fourth, the unstaged adjoint's launch bounds, was e3260ff's; none since)
        if len(blocks) > 4:
            psf_module._THREADS_TARGET["cuda"] = 1 << blocks[4]

    torch.manual_seed(0)
    image = torch.rand(*SHAPE, device="cuda")
    psf = torch.rand(SHAPE[1], *GRID, SIZE, SIZE, device="cuda", requires_grad=True)
    forward = time_cuda_graph(lambda: psf_conv(image, psf, "direct"))
    both = time_cuda_graph(lambda: torch.autograd.grad(psf_conv(image, psf, "direct").sum(), psf))
    out = psf_conv(image, psf, "direct")
    grad = torch.autograd.grad((out * torch.linspace(0, 1, SHAPE[-1], device="cuda")).sum(), psf)[0]
    record = {"rows": rows, "taps": taps, "blocks": blocks, "forward_ms": forward["median_ms"],
              "forward_iqr_ms": forward["iqr_ms"],
              "forward_psf_grad_ms": both["median_ms"], "forward_psf_grad_iqr_ms": both["iqr_ms"]}
    if reference:
        saved = torch.load(reference)
        record["forward_rel_diff"] = float((out - saved["out"]).abs().max() / saved["out"].abs().max())
        record["grad_rel_diff"] = float((grad - saved["grad"]).abs().max() / saved["grad"].abs().max())
    else:
        return {**record, "_save": {"out": out.detach(), "grad": grad}}
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", default="4,8,16")
    parser.add_argument("--taps", default="8,16")
    parser.add_argument("--json")
    parser.add_argument("--against", help="compare every variant with this reference (a first run's "
                        "/tmp/psf_reference.pt, e.g. of other kernels), rather than with the first variant")
    parser.add_argument("--blocks", default="", help="threads per block, forward/PSF adjoint pairs to time at the "
                        "shipped layout, e.g. 128/256,64/128 (with the ops' FORWARD_BLOCK and CELLS_BLOCK); a "
                        "third figure sets the forward's launch bounds (FORWARD_BLOCK, N blocks a multiprocessor), "
                        "e.g. 128/128/4; a fourth 0 (the unstaged PSF adjoint's launch bounds at e3260ff), a fifth log2 of the threads "
                        "the PSF adjoint's launch aims for, e.g. 128/128/5/0/17")
    parser.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        import torch

        rows, taps, reference = int(args.child[0]), int(args.child[1]), args.child[2]
        blocks = tuple(map(int, args.child[3].split("/"))) if args.child[3] != "-" else None
        record = measure(rows, taps, None if reference == "-" else reference, blocks)
        if "_save" in record:
            torch.save(record.pop("_save"), "/tmp/psf_reference.pt")
        print(json.dumps(record), flush=True)
        return
    variants = [(8, 8, "-")] + [(r, 8, "-") for r in map(int, args.rows.split(",")) if r != 8] + \
               [(8, t, "-") for t in map(int, args.taps.split(",")) if t != 8] + \
               [(8, 8, b) for b in args.blocks.split(",") if b] + [(8, 8, "-")]
    records = []
    for index, (rows, taps, blocks) in enumerate(variants):
        reference = args.against or ("-" if index == 0 else "/tmp/psf_reference.pt")
        # a kernel cache of its own: the layout constants must not meet another variant's compiled module
        cache = {**os.environ, "WARP_CACHE_PATH": f"/tmp/warp-cache-psf-{rows}-{taps}-{blocks.replace('/', '-')}"}
        done = subprocess.run([sys.executable, __file__, "--child", str(rows), str(taps), reference, blocks],
                              capture_output=True, text=True, env=cache)
        if done.returncode != 0:
            print(f"rows {rows} taps {taps} blocks {blocks}: failed: {done.stderr.strip().splitlines()[-1:]}",
                  flush=True)
            continue
        record = json.loads(done.stdout.strip().splitlines()[-1])
        records.append(record)
        print(json.dumps(record), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(records, indent=1))


if __name__ == "__main__":
    main()
