"""The composition root: the model users load (`SensingModel`), built from a config (`build_system`) or a
checkpoint (`load_system`), and the device a command runs on. Commands, tools and training build models through
here; `models/` holds networks only."""

from warpsense.system.build import build_system, check_config, load_system, load_teacher
from warpsense.system.checkpoint import CheckpointError, read_checkpoint, save_checkpoint
from warpsense.system.device import resolve_device
from warpsense.system.model import SensingModel

__all__ = [
    "CheckpointError", "SensingModel", "build_system", "check_config", "load_system", "load_teacher", "read_checkpoint",
    "resolve_device", "save_checkpoint",
]
