"""The GPUs of a study's local pool: which devices a worker's id names (`cuda_device`, within this process's
CUDA_VISIBLE_DEVICES), their busy fraction and free memory now (nvidia-smi, its rows matched to CUDA's ids by UUID)
and a sampler of the busy fraction while a study runs (`BusySampler`)."""

from __future__ import annotations

import functools
import os
import re
import subprocess
import sys
import threading


def visible_devices(environ=None) -> list[str] | None:
    """The entries of this process's ``CUDA_VISIBLE_DEVICES`` (indices, GPU-... or MIG-... UUIDs; an empty value:
    none), or None where it is unset (every GPU of the machine is visible)."""
    value = (os.environ if environ is None else environ).get("CUDA_VISIBLE_DEVICES")
    return None if value is None else [entry.strip() for entry in value.split(",") if entry.strip()]


def cuda_device(gpu: str, environ=None) -> str:
    """The ``CUDA_VISIBLE_DEVICES`` value of a child process that is to use pool id ``gpu``. Pool ids (``--gpus``)
    count within this process's visible devices, as torch's ``cuda:N`` does: with CUDA_VISIBLE_DEVICES=2,3 (a
    Slurm allocation, a shared node) id 0 is entry "2", whereas a bare "0" in the child would name the machine's
    GPU 0, someone else's. Unset: the id itself. ValueError naming --gpus for an id past the visible entries."""
    visible = visible_devices(environ)
    if visible is None:
        return gpu
    if int(gpu) >= len(visible):
        shown = ",".join(visible) or "(empty: no GPU)"
        raise ValueError(f"--gpus {gpu}: no such GPU; ids count within CUDA_VISIBLE_DEVICES={shown} as in PyTorch "
                         f"({len(visible)} visible{f', ids 0-{len(visible) - 1}' if visible else ''})")
    return visible[int(gpu)]


_CUDA_UUIDS = "import torch\nfor i in range(torch.cuda.device_count()): print(torch.cuda.get_device_properties(i).uuid)"
_UUID = re.compile(r"[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}")


@functools.lru_cache(maxsize=None)
def cuda_uuids(gpus: tuple[str, ...]) -> tuple[str, ...] | None:
    """The UUID of the GPU each pool id names (lower-case hex, no "GPU-"), None where it cannot be read.

    A pool id is CUDA's (a worker's CUDA_VISIBLE_DEVICES), counted in CUDA_DEVICE_ORDER's order (FASTEST_FIRST by
    default), whereas nvidia-smi's index is its PCI bus order: the two agree only by chance, so `_query_gpus` matches
    the rows by UUID. A short child process with CUDA_VISIBLE_DEVICES set to the ids' devices (`cuda_device`, as
    the workers' own), reads them through torch, so that this long-lived process holds no CUDA context (~0.5 GB on
    each GPU for the whole study). Cached: the sampler asks every 2 s."""
    try:
        environment = {**os.environ, "CUDA_VISIBLE_DEVICES": ",".join(cuda_device(gpu) for gpu in gpus)}
    except ValueError:  # an id past CUDA_VISIBLE_DEVICES: no GPU to read
        return None
    try:
        result = subprocess.run([sys.executable, "-c", _CUDA_UUIDS], env=environment, capture_output=True, text=True,
                                timeout=120, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    uuids = tuple(_UUID.findall(result.stdout.lower()))
    return uuids if len(uuids) == len(gpus) else None


def _query_gpus(field: str, gpus: list[str]) -> list[float] | None:
    """nvidia-smi's ``field`` (a --query-gpu name) of each GPU id now; None where it cannot be read. The rows are
    matched to the ids by UUID (`cuda_uuids`); by position only where nvidia-smi lists one GPU and the id is 0."""
    try:
        result = subprocess.run(["nvidia-smi", f"--query-gpu=uuid,{field}", "--format=csv,noheader,nounits"],
                                capture_output=True, text=True, timeout=10, check=True)
        rows = [line.replace(" ", "").lower().split(",")[:2] for line in result.stdout.strip().splitlines()]
        if len(rows) == 1 and set(gpus) == {"0"}:  # one GPU: CUDA's 0 is it whatever the order
            return [float(rows[0][1])] * len(gpus)
        unique = tuple(dict.fromkeys(gpus))
        uuids = cuda_uuids(unique)
        if uuids is None:
            return None
        values = {_UUID.search(uuid).group(): float(value) for uuid, value in rows}
        by_id = {gpu: values[uuid] for gpu, uuid in zip(unique, uuids)}
        return [by_id[gpu] for gpu in gpus]
    except (OSError, subprocess.SubprocessError, ValueError, KeyError, AttributeError):
        return None


def gpu_busy(gpus: list[str]) -> list[float] | None:
    """Busy percentage (0-100) of each GPU id now, from nvidia-smi; None where it cannot be read."""
    return _query_gpus("utilization.gpu", gpus)


def gpu_memory_gib(gpus: list[str]) -> list[float] | None:
    """Free memory of each GPU id in GiB now (before the pool's workers start: what its cells can have, less what
    other users' processes hold), from nvidia-smi; None where it cannot be read."""
    free = _query_gpus("memory.free", gpus)  # MiB
    return None if free is None else [mib / 1024 for mib in free]


class BusySampler:
    """Samples `gpu_busy` every ``interval`` seconds on a thread while a study runs; ``fractions()`` is each GPU's
    mean busy fraction in [0, 1] (None when nothing could be sampled)."""

    def __init__(self, gpus: list[str], interval: float = 2.0):
        self.gpus, self.interval, self.samples = gpus, interval, []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            sample = gpu_busy(self.gpus)
            if sample is None:
                return
            self.samples.append(sample)
            self._stop.wait(self.interval)

    def __enter__(self) -> "BusySampler":
        if self.gpus:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=15)

    def fractions(self) -> list[float] | None:
        if not self.samples:
            return None
        return [sum(sample[i] for sample in self.samples) / len(self.samples) / 100 for i in range(len(self.gpus))]
