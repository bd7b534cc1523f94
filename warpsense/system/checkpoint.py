"""Checkpoints: one safetensors file (no pickle) holding the tensors and, in its metadata, the resolved config and
training state; a JSON copy of that metadata is written beside it for people to read.

The checkpoint is one file, written to a temporary name and renamed: a kill at any moment leaves either the old
checkpoint or the new one, never a mix (metadata in a file of its own could be replaced apart from the tensors it
describes). Reading takes the metadata inside the file; the sidecar is consulted only for older checkpoints that hold
none.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from warpsense.errors import first_line
from warpsense.files import atomic_write, located, write_json

METADATA_KEY = "warpsense"


class CheckpointError(ValueError):
    """A checkpoint that cannot be read or does not describe a warpsense run (message names the file)."""


def save_checkpoint(path: str | Path, model: torch.nn.Module, config_dict: dict, state: dict,
                    optimizer: torch.optim.Optimizer | None = None, rng_state: torch.Tensor | None = None) -> None:
    """Write ``path`` (.safetensors, atomically) and a readable copy of its metadata at ``path.with_suffix('.json')``.

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
    payload = {"config": config_dict, "state": state}
    with atomic_write(path) as temporary:
        save_file(tensors, str(temporary), metadata={METADATA_KEY: json.dumps(payload, sort_keys=True)})
    write_json(readable_copy(path), payload, sort_keys=True)


def readable_copy(path: str | Path) -> Path:
    """The JSON copy of a checkpoint's metadata written beside it (`save_checkpoint`), for people to read."""
    return Path(path).with_suffix(".json")


def read_checkpoint(path: str | Path) -> tuple[dict[str, torch.Tensor], dict]:
    """(tensors, {"config": ..., "state": ...}); every failure is a one-line `CheckpointError` naming the file."""
    path = _checkpoint_file(path)
    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = handle.metadata() or {}
        tensors = load_file(str(path))
    except Exception as error:  # safetensors raises several types for zero-byte, truncated or foreign files
        raise CheckpointError(f"{path}: not a readable safetensors checkpoint ({first_line(error)})") from None
    meta = _run_metadata(path, metadata)
    if not any(name.startswith("model.") for name in tensors):
        raise CheckpointError(f"{path}: holds no model tensors")
    return tensors, meta


def read_header(path: str | Path) -> dict:
    """{"config": ..., "state": ...} of a checkpoint from its header alone (no tensor is read: a run's status or
    its kept best score without loading megabytes); failures as `read_checkpoint`'s, but for a file without model
    tensors, which only reading the tensors tells."""
    path = _checkpoint_file(path)
    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = handle.metadata() or {}
    except Exception as error:  # as read_checkpoint's: several types for zero-byte, truncated or foreign files
        raise CheckpointError(f"{path}: not a readable safetensors checkpoint ({first_line(error)})") from None
    return _run_metadata(path, metadata)


def _checkpoint_file(path: str | Path) -> Path:
    """``path`` as a checkpoint file to read: a folder, a missing file or the readable .json copy is a one-line
    error naming it."""
    path = Path(path)
    if path.is_dir():
        raise FileNotFoundError(f"{path}: is a folder; name its checkpoint file (e.g. {path}/checkpoint_best"
                                ".safetensors)")
    if not path.is_file():
        raise FileNotFoundError(f"{located(path)}: checkpoint not found")
    if path.suffix.lower() == ".json" and path.with_suffix(".safetensors").is_file():
        raise CheckpointError(f"{path}: the readable copy of a checkpoint; name {path.with_suffix('.safetensors')}")
    return path


def _run_metadata(path: Path, metadata: dict) -> dict:
    """The run's {"config", "state"} from a checkpoint's safetensors ``metadata``, or from the .json beside it for a
    checkpoint written before the metadata went inside."""
    if METADATA_KEY in metadata:
        text, source = metadata[METADATA_KEY], f"{path} metadata"
    else:
        sidecar = readable_copy(path)
        if not sidecar.is_file():
            raise CheckpointError(f"{path}: no run metadata inside and no {sidecar.name} beside it")
        try:
            text, source = sidecar.read_text(), str(sidecar)
        except (OSError, UnicodeDecodeError) as error:
            raise CheckpointError(f"{sidecar}: unreadable ({first_line(error)})") from None
    try:
        meta = json.loads(text)
    except (ValueError, RecursionError) as error:  # JSONDecodeError; a 5000-digit number, deep nesting
        raise CheckpointError(f"{source}: invalid JSON ({first_line(error)})") from None
    if not (isinstance(meta, dict) and isinstance(meta.get("config"), dict) and isinstance(meta.get("state"), dict)):
        raise CheckpointError(f"{source}: expected an object with 'config' and 'state' objects")
    return meta


def restore(tensors: dict, model: torch.nn.Module, optimizer: torch.optim.Optimizer | None = None,
            source: str | Path = "checkpoint") -> None:
    """Load model (and optimizer) state from `read_checkpoint` tensors of the file ``source``; tensors that do not
    fit the model (names or shapes) are a one-line `CheckpointError` naming it."""
    try:
        _load_states(tensors, model, optimizer)
    except (RuntimeError, KeyError, ValueError, IndexError) as error:
        raise CheckpointError(f"{source}: its tensors do not fit the model its config builds "
                              f"({first_line(error)[:200]})") from None


def _load_states(tensors: dict, model: torch.nn.Module, optimizer: torch.optim.Optimizer | None) -> None:
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
        # the file holds contiguous tensors; fused AdamW needs each moment laid out like its (channels-last) parameter
        for group in optimizer.param_groups:
            for parameter in group["params"]:
                for key, value in optimizer.state.get(parameter, {}).items():
                    if (torch.is_tensor(value) and value.shape == parameter.shape
                            and value.stride() != parameter.stride()):
                        optimizer.state[parameter][key] = torch.empty_like(parameter, dtype=value.dtype).copy_(value)


RESUME_STATE = {"epoch": int, "step": int, "best_miou": float}


def resume_state(checkpoint: str | Path, tensors: dict, meta: dict) -> dict:
    """The training state a resume needs (epoch, step, best mIoU and the RNG tensor), checked: a checkpoint
    without them is a one-line `CheckpointError`."""
    state = meta["state"]
    for key, kind in RESUME_STATE.items():
        value = state.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float) if kind is float else kind):
            raise CheckpointError(f"{checkpoint}: state.{key} must be {'a number' if kind is float else 'an int'}, "
                                  f"got {value!r} (not a checkpoint_last of a training run?)")
    if "rng" not in tensors or tensors["rng"].dtype != torch.uint8:
        raise CheckpointError(f"{checkpoint}: no RNG state (not a checkpoint_last of a training run?)")
    return state
