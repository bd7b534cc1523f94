"""CUDA MPS (Multi-Process Service) for a study's local pool: several cells on one GPU that really run at once.

Without MPS a GPU time-slices the CUDA contexts of separate processes, so two cells on one GPU each get about half of
it (plus switching cost); with MPS their kernels share the GPU's SMs concurrently, so a cell's small kernels fill
the SMs another cell leaves idle (the measured gains: docs/benchmarks.md, studies per GPU-hour).

The pool starts its own control daemon (``nvidia-cuda-mps-control -d``) with pipe and log directories in a fresh
temporary folder, passes them to its worker processes (``CUDA_MPS_PIPE_DIRECTORY``, ``CUDA_MPS_LOG_DIRECTORY``) and
stops it (``quit``) when the pool ends, so a study neither needs nor disturbs a daemon the user runs.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

from warpsense.choices import MPS_MODES

CONTROL = "nvidia-cuda-mps-control"


class MPSError(RuntimeError):
    """The MPS daemon was asked for and could not start; the message says why."""


def check_mode(mode: str) -> None:
    """ValueError naming ``--mps`` for a mode not in `MPS_MODES`."""
    if mode not in MPS_MODES:
        raise ValueError(f"--mps must be one of {', '.join(MPS_MODES)}, got {mode!r}")


def wanted(mode: str, per_gpu: int) -> bool:
    """Whether the pool runs under MPS: ``mode`` "on", or "auto" with ``per_gpu`` > 1 and the control program on the
    PATH. Raises MPSError for "on" without the control program, ValueError for an unknown mode."""
    check_mode(mode)
    if mode == "off":
        return False
    found = shutil.which(CONTROL) is not None
    if mode == "on" and not found:
        raise MPSError(f"--mps on: {CONTROL} is not on the PATH (CUDA MPS comes with the NVIDIA driver)")
    return found and (mode == "on" or per_gpu > 1)


AUTO_CELLS = 3
"""Cells a GPU takes under ``--per-gpu auto`` with MPS: three cells of the presets' recipe a GPU gave the most cells
per GPU-hour measured, with each cell's score within the seeds' spread (docs/benchmarks.md, studies per GPU-hour)."""

CELL_MEMORY_GIB = 14.1
"""GPU memory a worker of the presets' recipe held at its peak (batch 16 at 352 x 480, CUDA graphs, evaluation; the
largest of four workers as nvidia-smi counted it, 9.3-14.1 GiB, the two that trained cells of all three folds ~14,
docs/records/answers/alone_memory_peaks.json)."""

CELL_FIXED_GIB = 0.9
"""Of `CELL_MEMORY_GIB`, what does not grow with a step's pixels (the CUDA context, weights, workspaces): one process
held 8.81 GiB at batch 16 and 16.73 at 32 after training and evaluating (nvidia-smi; docs/records/answers/memory*.json),
0.9 GiB at none."""

RECIPE_PIXELS = 16 * 352 * 480
"""Pixels a training step of the presets' recipe (batch x crop)."""


def cell_memory_gib(pixels: int) -> float:
    """Estimated GPU memory of one cell whose training step holds ``pixels`` (batch x crop height x width): the
    recipe's measured footprint scaled in its part that grows with the activations."""
    return CELL_FIXED_GIB + (CELL_MEMORY_GIB - CELL_FIXED_GIB) * pixels / RECIPE_PIXELS


def auto_cells_per_gpu(mode: str, memory_gib: list[float] | None, pixels: int) -> tuple[int, str]:
    """``--per-gpu auto``: `AUTO_CELLS` cells a GPU where the pool runs under MPS (``mode`` as `wanted` reads it)
    and the smallest GPU holds them with 10% to spare by `cell_memory_gib`, fewer where it holds fewer, and one
    without MPS (time-sliced cells were no faster together: docs/benchmarks.md). ``memory_gib``: each GPU's
    memory free for the pool (None: unknown, one cell a GPU). Returns the count and why, in words."""
    if not wanted(mode, AUTO_CELLS):
        return 1, "without CUDA MPS cells sharing a GPU are time-sliced"
    if not memory_gib:
        return 1, "the GPUs' memory could not be read (nvidia-smi)"
    need = cell_memory_gib(pixels)
    fits = int(0.9 * min(memory_gib) // need)
    count = max(1, min(AUTO_CELLS, fits))
    held = f"{min(memory_gib):.0f} GiB free a GPU, ~{need:.1f} GiB a cell"
    return count, (f"CUDA MPS, {held}" if count > 1 else f"{held}: one fits with 10% to spare")


@contextlib.contextmanager
def mps_daemon(enabled: bool) -> Iterator[dict[str, str]]:
    """Run an MPS control daemon for the duration of the block; yields the environment variables its clients (the
    pool's workers) need ({} when not ``enabled``). The daemon is stopped, and its folder removed, on exit."""
    if not enabled:
        yield {}
        return
    folder = Path(tempfile.mkdtemp(prefix="warpsense-mps-"))
    environment = {"CUDA_MPS_PIPE_DIRECTORY": str(folder / "pipe"), "CUDA_MPS_LOG_DIRECTORY": str(folder / "log")}
    for path in environment.values():
        Path(path).mkdir()
    env = {**os.environ, **environment}
    try:
        started = subprocess.run([CONTROL, "-d"], env=env, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError) as error:
        shutil.rmtree(folder, ignore_errors=True)
        raise MPSError(f"{CONTROL} -d: {error}") from None
    if started.returncode != 0:
        shutil.rmtree(folder, ignore_errors=True)
        raise MPSError(f"{CONTROL} -d exited {started.returncode}: {(started.stderr or started.stdout).strip()}")
    try:
        yield environment
    finally:
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            subprocess.run([CONTROL], input="quit\n", env=env, capture_output=True, text=True, timeout=30)
        shutil.rmtree(folder, ignore_errors=True)
