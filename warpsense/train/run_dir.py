"""A training run's directory: where a new run goes, which run `--resume` means, the config a resumed run keeps,
its metrics log, and a lock so that two trainings never write into one run."""

from __future__ import annotations

import json
import math
import os
import re
import socket
from pathlib import Path

from warpsense.config import Config, ConfigError, config_from_dict, flatten_keys
from warpsense.errors import first_line

LAST = "checkpoint_last.safetensors"
BEST = "checkpoint_best.safetensors"
METRICS = "metrics.jsonl"  # one JSON record per epoch
LOCK = "train.lock"
# keys a resumed run may change without asking: where the run is found and which device it runs on
RELOCATABLE_KEYS = ("run.output_dir", "run.name", "run.device")
# keys that make a run another task (what it trains and is judged on, its classes, its network's shape), refused for
# a continued run even with --allow-config-change: its checkpoints, metrics and evaluation would mix two tasks. Every
# "<section>.enabled" (a camera stage or the ISP turned on or off) counts too (`task_changes`).
TASK_KEYS = ("data.dataset", "data.root", "data.train_split", "data.val_split", "data.holdout_prefix",
             "data.holdout_sequence", "data.holdout_block", "data.holdout_blocks", "data.block_buffer",
             "model.num_classes", "model.name", "model.width", "model.context",
             "model.squeeze", "model.full_width", "model.full_depth", "model.input", "cfa.tile")


def holds_run(folder: Path) -> bool:
    """Whether ``folder`` holds a run: its resume point, or a best checkpoint (a run interrupted before its first
    resume point keeps the best one it wrote: a model of the user's)."""
    return (Path(folder) / LAST).exists() or (Path(folder) / BEST).exists()


def fresh_run_dir(base: Path) -> Path:
    """``base`` if it holds no run yet (`holds_run`), else the first free ``base-N`` (N = 2, 3, ...)."""
    if not holds_run(base):
        return base
    suffix = 2
    while holds_run(base.parent / f"{base.name}-{suffix}"):
        suffix += 1
    return base.parent / f"{base.name}-{suffix}"


def set_aside(folder: Path) -> Path:
    """Rename a run folder that has no resume point but a best checkpoint (`holds_run`: a run interrupted before its
    first resume point) to ``<name>.interrupted`` (then ``.interrupted-2``, ...), so that a run that must have this
    folder (a study's cell) starts again there without overwriting that best checkpoint; returns the new path."""
    folder = Path(folder)
    target = folder.with_name(f"{folder.name}.interrupted")
    suffix = 2
    while target.exists():
        target = folder.with_name(f"{folder.name}.interrupted-{suffix}")
        suffix += 1
    folder.rename(target)
    return target


def newest_run(output_dir: str | Path, name: str) -> Path:
    """The run `--resume` continues: of <output_dir>/<name> and <output_dir>/<name>-N that hold a last checkpoint,
    the one with the highest N (the most recently started)."""
    output_dir = Path(output_dir)
    pattern = re.compile(rf"^{re.escape(name)}(?:-(\d+))?$")
    runs = []
    if output_dir.is_dir():
        for entry in output_dir.iterdir():
            match = pattern.match(entry.name)
            if match and (entry / LAST).is_file():
                runs.append((int(match.group(1) or 1), entry))
    if not runs:
        raise FileNotFoundError(f"no run named {name!r} with a checkpoint in {output_dir} to resume")
    return max(runs)[1]


def config_changes(saved: Config, requested: Config) -> list[str]:
    """``section.key: saved -> requested`` for every key that differs, relocatable keys left out."""
    before, after = flatten_keys(saved.to_dict()), flatten_keys(requested.to_dict())
    return [f"{key}: {before.get(key)!r} -> {after.get(key)!r}" for key in sorted(set(before) | set(after))
            if key not in RELOCATABLE_KEYS and before.get(key) != after.get(key)]


JUDGED_KEYS = ("data.classes_file", "data.max_val_images", "data.scenes_val", "data.scene_height", "data.scene_width",
               "data.scene_sequences")
"""Keys of the task too (`is_task_key`): the folder dataset's class table (its content is compared on its own:
`warpsense.train.inputs`), and the frames a run is judged on (how many; the generated scenes' size and sequences)."""


def is_task_key(key: str) -> bool:
    """Whether changing ``key`` ("section.key") makes a run another task: `TASK_KEYS`, `JUDGED_KEYS` and every
    "<section>.enabled"."""
    return key in TASK_KEYS or key in JUDGED_KEYS or key.endswith(".enabled")


def task_changes(saved: Config, requested: Config) -> list[str]:
    """The entries of `config_changes` whose key `is_task_key`."""
    return [change for change in config_changes(saved, requested) if is_task_key(change.split(":", 1)[0])]


def resumed_config(run_dir: Path, requested: Config | None, allow_change: bool = False) -> Config:
    """The config a resumed run trains with: its own config.json. A ``requested`` config that differs from it (other
    than `RELOCATABLE_KEYS`) is refused with the differing keys named, unless ``allow_change``; then it is used. A
    change of task (`task_changes`) is refused either way: that is a new run. An allowed change is printed (the keys,
    old -> new). Reads only; writes nothing."""
    path = run_dir / "config.json"
    try:
        data = json.loads(path.read_text())
    except OSError as error:
        raise ConfigError(f"{path}: cannot read the run's config: {error.strerror}") from None
    except (ValueError, RecursionError) as error:  # JSONDecodeError, UnicodeDecodeError (a torn or foreign file)
        raise ConfigError(f"{path}: invalid JSON: {first_line(error)}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a JSON object of config sections, got {type(data).__name__}")
    saved = config_from_dict(data, str(path))
    if requested is None:
        return saved
    changes = config_changes(saved, requested)
    task = task_changes(saved, requested)
    if task:
        raise ConfigError(f"resuming {run_dir}: {'; '.join(task)} would make it another task (data, classes, network "
                          "shape or camera stages), so it is not continued and nothing in it changed; train it as a "
                          "new run (without --resume/--resume-dir)")
    if changes and not allow_change:
        raise ConfigError(f"resuming {run_dir} with a config that differs from the run's ({'; '.join(changes)}); "
                          "drop --config/--set to continue as it was, or pass --allow-config-change")
    if not changes:
        saved.run.device = requested.run.device  # the device may change; where the run lives stays the run's
        return saved
    from warpsense.train.distributed import launch_rank  # here: the command parsers import this module, not torch

    if launch_rank() == 0:  # allowed, but never silent; said once under torchrun (no process group yet)
        print(f"resuming {run_dir} with config changes: {'; '.join(changes)}")
    return requested


METRIC_SECONDS = ("wall_s", "setup_s", "setup_data_s", "epoch_time_s", "capture_s")
"""The times of a metrics record that readers add up (the report's run times, the study suite's)."""


def read_metrics(path: Path, up_to_epoch: int | None = None) -> list[dict]:
    """The records of metrics.jsonl up to ``up_to_epoch`` (None: all of them); a torn (unparsable) last line, left by
    a kill while it was written, is dropped. A torn line elsewhere, a line that is not a JSON object, an epoch that
    is not an integer >= 0 or a time (`METRIC_SECONDS`) that is not a finite number >= 0 is a one-line ValueError
    naming the file, line and field."""
    path = Path(path)
    if not path.exists():
        return []
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: unreadable: {first_line(error)}") from None
    lines = [(number, line) for number, line in enumerate(text.splitlines(), start=1) if line.strip()]
    records = []
    for index, (number, line) in enumerate(lines):
        try:
            record = json.loads(line)
        except (ValueError, RecursionError):
            if index == len(lines) - 1:
                break
            raise ValueError(f"{path}:{number}: not a JSON record") from None
        records.append(_checked_metrics(record, f"{path}:{number}"))
    if up_to_epoch is None:
        return records
    return [r for r in records if r.get("epoch", up_to_epoch + 1) <= up_to_epoch]


def _checked_metrics(record, where: str) -> dict:
    """One metrics record, its epoch and times checked (`read_metrics`)."""
    if not isinstance(record, dict):
        raise ValueError(f"{where}: expected a JSON object (an epoch's record), got {type(record).__name__}")
    epoch = record.get("epoch", 0)
    if isinstance(epoch, bool) or not isinstance(epoch, int) or epoch < 0:
        raise ValueError(f"{where}: epoch: expected an integer >= 0, got {epoch!r}")
    for field in METRIC_SECONDS:
        value = record.get(field, 0.0)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise ValueError(f"{where}: {field}: expected a finite number of seconds >= 0, got {value!r}")
    return record


class RunLock:
    """An exclusive lock on a run directory: a file holding the owner's pid and host name, created atomically. A lock
    left by a process of this machine that no longer runs is taken over. A lock of another host (a run directory on
    a shared disk) cannot be checked from here: a Slurm task takes it over (the scheduler runs a cell's task once, so
    it is the lock of that task, killed on its node), anything else is refused naming the host."""

    def __init__(self, run_dir: Path):
        self.path = Path(run_dir) / LOCK
        self.held = False

    def acquire(self) -> "RunLock":
        for _ in range(2):
            try:
                descriptor = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                owner = self._owner()
                if owner is not None and _elsewhere(owner[1]) and "SLURM_JOB_ID" not in os.environ:
                    raise FileExistsError(f"run directory {self.path.parent} is locked by process {owner[0]} on "
                                          f"{owner[1]} (remove {self.path} if that process is not training)") from None
                if owner is not None and not _elsewhere(owner[1]) and _alive(owner[0]):
                    raise FileExistsError(f"run directory {self.path.parent} is in use by process {owner[0]} "
                                          f"(remove {self.path} if that process is not training)") from None
                self.path.unlink(missing_ok=True)  # stale: its owner is gone
                continue
            with os.fdopen(descriptor, "w") as handle:
                handle.write(f"{os.getpid()} {socket.gethostname()}")
            self.held = True
            return self
        raise FileExistsError(f"cannot lock run directory {self.path.parent}")

    def release(self) -> None:
        if self.held:
            self.path.unlink(missing_ok=True)
            self.held = False

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()

    def holder(self) -> int | None:
        """The pid of the live process of this machine that holds the lock, if any (a stale lock's, or another
        host's, is None)."""
        owner = self._owner()
        return owner[0] if owner is not None and not _elsewhere(owner[1]) and _alive(owner[0]) else None

    def _owner(self) -> tuple[int, str | None] | None:
        """(pid, host) of the lock's owner; host None for a lock of the older form (a pid alone: this machine's)."""
        try:
            words = self.path.read_text().split()
            return int(words[0]), (words[1] if len(words) > 1 else None)
        except (OSError, ValueError, IndexError):
            return None


def _elsewhere(host: str | None) -> bool:
    return host is not None and host != socket.gethostname()


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
