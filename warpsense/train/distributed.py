"""torch.distributed set-up for `torchrun` launches (DDP); a no-op context for single-process runs."""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

from warpsense.system.device import resolve_device


def launch_rank() -> int:
    """This process's rank as torchrun set it (RANK; 0 without torchrun), readable before any process group."""
    return int(os.environ.get("RANK", "0"))


@dataclass
class DistributedContext:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @classmethod
    def from_environment(cls, device_choice: str = "auto") -> "DistributedContext":
        """Read torchrun's RANK / WORLD_SIZE / LOCAL_RANK; initialise the process group (NCCL on CUDA, gloo on
        CPU) and pick this rank's device (cuda:LOCAL_RANK)."""
        world_size = int(os.environ.get("WORLD_SIZE", "1"))
        rank = launch_rank()
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        use_cuda = resolve_device(device_choice).type == "cuda"
        if device_choice == "cuda" and not torch.cuda.is_available():
            raise RuntimeError("run.device = cuda but no CUDA device is available")
        device = torch.device("cuda", local_rank if world_size > 1 else torch.cuda.current_device()) if use_cuda \
            else torch.device("cpu")
        if use_cuda:
            torch.cuda.set_device(device)
        if world_size > 1 and not dist.is_initialized():
            dist.init_process_group("nccl" if use_cuda else "gloo", rank=rank, world_size=world_size)
        return cls(rank, world_size, local_rank, device)

    def all_reduce_sum(self, tensor: torch.Tensor) -> torch.Tensor:
        if self.enabled:
            dist.all_reduce(tensor, op=dist.ReduceOp.SUM)
        return tensor

    def barrier(self) -> None:
        if self.enabled:
            dist.barrier()

    def close(self) -> None:
        if self.enabled and dist.is_initialized():
            dist.destroy_process_group()


def wrap_data_parallel(model: torch.nn.Module, device: torch.device) -> torch.nn.Module:
    """DDP without the per-forward buffer broadcast, as the runs have always trained: each rank keeps its own
    BatchNorm statistics (on CUDA they are synchronised by SyncBatchNorm instead) and checkpoints hold rank 0's.
    torch >= 2.13 spells this ``forward_sync_buffers=False`` (buffers still broadcast once at construction, where
    they are equal anyway) and warns about ``broadcast_buffers``; older versions take ``broadcast_buffers=False``."""
    import inspect

    from torch.nn.parallel import DistributedDataParallel

    device_ids = [device.index] if device.type == "cuda" else None
    if "forward_sync_buffers" in inspect.signature(DistributedDataParallel.__init__).parameters:
        return DistributedDataParallel(model, device_ids=device_ids, forward_sync_buffers=False)
    return DistributedDataParallel(model, device_ids=device_ids, broadcast_buffers=False)
