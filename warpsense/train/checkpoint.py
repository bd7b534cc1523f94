"""Checkpoints: safetensors (no pickle) + a JSON sidecar with the resolved config and training state.

Both files are written to temporary names and renamed, so an interrupted write never leaves a partial checkpoint.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file


def _atomic_json(path: Path, payload: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2, sort_keys=True))
    os.replace(tmp, path)


def save_checkpoint(path: str | Path, model: torch.nn.Module, config_dict: dict, state: dict,
                    optimizer: torch.optim.Optimizer | None = None, rng_state: torch.Tensor | None = None) -> None:
    """Write ``path`` (.safetensors) and ``path.with_suffix('.json')``.

    Tensors: ``model.*`` (state dict), ``optimizer.<param index>.<key>`` (AdamW moments and step), ``rng`` (torch
    CPU generator state). JSON: {"config": ..., "state": ...} with the epoch, step, best mIoU, CFA layout etc.
    """
    path = Path(path)
    tensors = {f"model.{k}": v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
    if optimizer is not None:
        for index, param_state in optimizer.state_dict()["state"].items():
            for key, value in param_state.items():
                tensors[f"optimizer.{index}.{key}"] = torch.as_tensor(value).detach().contiguous().cpu()
    if rng_state is not None:
        tensors["rng"] = rng_state
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp))
    _atomic_json(path.with_suffix(".json"), {"config": config_dict, "state": state})
    os.replace(tmp, path)


def read_checkpoint(path: str | Path) -> tuple[dict[str, torch.Tensor], dict]:
    """(tensors, {"config": ..., "state": ...}); errors name the file."""
    path = Path(path)
    sidecar = path.with_suffix(".json")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    if not sidecar.is_file():
        raise FileNotFoundError(f"{sidecar}: checkpoint config (JSON sidecar) not found")
    return load_file(str(path)), json.loads(sidecar.read_text())


def restore(tensors: dict, model: torch.nn.Module, optimizer: torch.optim.Optimizer | None = None) -> None:
    """Load model (and optimizer) state from `read_checkpoint` tensors."""
    model.load_state_dict({k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")})
    if optimizer is not None:
        state_dict = optimizer.state_dict()
        restored = {}
        for name, value in tensors.items():
            if name.startswith("optimizer."):
                _, index, key = name.split(".", 2)
                restored.setdefault(int(index), {})[key] = value
        state_dict["state"] = restored
        optimizer.load_state_dict(state_dict)
