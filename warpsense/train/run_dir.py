"""A training run's directory: the files in it and how each is read and written (`RunDir`, the one place that names
them), where a new run goes, which run `--resume` means, the config a resumed run keeps, its metrics log, and a lock
so that two trainings never write into one run."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import socket
from pathlib import Path

from warpsense.config import Config, ConfigError, config_from_dict, flatten_keys
from warpsense.errors import first_line
from warpsense.files import Folder, atomic_write, write_json


class RunDir(Folder):
    """A training run's directory: the one owner of its files' names and of how each is read and written.

    Files: `CONFIG` (the run's resolved config, `Config.save`; a continuation that changed it keeps the earlier one
    as config.epoch<E>.json, `earlier_config`), `METRICS` (one JSON record per epoch), the checkpoints `LAST` (the
    resume point: weights, optimizer, RNG) and `BEST` (the best-scoring epoch's weights), each with a readable JSON
    copy of its header beside it, `EVALUATION` (the final evaluation; present once the run is finished),
    `ENVIRONMENT` (versions and source commit), `INPUTS` (the digests of the files it read, `warpsense.train.inputs`),
    the plots (``<name>.png``) and `LOCK` (`RunLock`). Readers of damaged files raise one-line errors naming the file
    and field (`read_metrics`, `warpsense.system.checkpoint`); writers write atomically (`warpsense.files`).

    Args:
        path: the run directory (it need not exist yet).
    """

    CONFIG = "config.json"
    METRICS = "metrics.jsonl"
    LAST = "checkpoint_last.safetensors"
    BEST = "checkpoint_best.safetensors"
    EVALUATION = "evaluation.json"
    ENVIRONMENT = "environment.json"
    INPUTS = "inputs.json"
    """{"files": {path: {"key": the config key that named it, "sha256": its content's digest}}}."""
    LOCK = "train.lock"

    # --- where each file is ------------------------------------------------------------------------------------

    @property
    def config(self) -> Path:
        return self.path / self.CONFIG

    @property
    def metrics(self) -> Path:
        return self.path / self.METRICS

    @property
    def last(self) -> Path:
        return self.path / self.LAST

    @property
    def best(self) -> Path:
        return self.path / self.BEST

    @property
    def evaluation(self) -> Path:
        return self.path / self.EVALUATION

    @property
    def environment(self) -> Path:
        return self.path / self.ENVIRONMENT

    @property
    def inputs(self) -> Path:
        return self.path / self.INPUTS

    @property
    def best_copy(self) -> Path:
        """The readable JSON copy of the best checkpoint's header."""
        from warpsense.system.checkpoint import readable_copy

        return readable_copy(self.best)

    def earlier_config(self, epoch: int) -> Path:
        """Where a continuation from ``epoch`` keeps the config the epochs before it trained with."""
        return self.path / superseded_name(self.CONFIG, epoch)

    def plot(self, name: str) -> Path:
        """The run's plot ``name`` (curves, design, camera, predictions) as a PNG."""
        return self.path / f"{name}.png"

    # --- what it holds -------------------------------------------------------------------------------------------

    def holds_run(self) -> bool:
        """Whether it holds a run: its resume point, or a best checkpoint (a run interrupted before its first resume
        point keeps the best one it wrote: a model of the user's)."""
        return self.last.exists() or self.best.exists()

    def resumable(self) -> bool:
        """Whether it holds a resume point (`LAST`)."""
        return self.last.is_file()

    def finished(self) -> bool:
        """Whether its final evaluation is written (`EVALUATION`: after the plan's last epoch)."""
        return self.evaluation.is_file()

    # --- config --------------------------------------------------------------------------------------------------

    def read_config(self) -> dict:
        """The saved config's sections as JSON (`CONFIG`); a one-line ConfigError naming the file where it cannot
        be read or is not a JSON object."""
        path = self.config
        try:
            data = json.loads(path.read_text())
        except OSError as error:
            raise ConfigError(f"{path}: cannot read the run's config: {error.strerror}") from None
        except (ValueError, RecursionError) as error:  # JSONDecodeError, UnicodeDecodeError (a torn or foreign file)
            raise ConfigError(f"{path}: invalid JSON: {first_line(error)}") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: expected a JSON object of config sections, got {type(data).__name__}")
        return data

    def saved_config(self) -> Config:
        """The run's own config (`read_config`, read as this version reads a config)."""
        return config_from_dict(self.read_config(), str(self.config))

    def write_config(self, config: Config, continued_from: int | None = None) -> None:
        """Write ``config`` as the run's `CONFIG` (atomically). A continuation (``continued_from``: its first epoch)
        whose config differs from the saved one first copies that to `earlier_config`, the config the epochs before
        it trained with (one already there is that config, from an earlier continuation of the same epoch that kept
        no epoch of its own, and stays); a copy, not a move, so that a kill between the two writes still leaves a
        config."""
        saved = self.config
        if continued_from is not None and saved.is_file() and \
                json.loads(saved.read_text()) != json.loads(json.dumps(config.to_dict())):
            earlier = self.earlier_config(continued_from)
            if not earlier.exists():
                with atomic_write(earlier) as temporary:
                    shutil.copyfile(saved, temporary)
        config.save(saved)

    def write_run_files(self, config: Config, versions: dict, history: list[dict], continued_from: int | None = None,
                        inputs: dict | None = None) -> None:
        """The run's config (`write_config`), environment (``versions``), metrics (``history``: the records it
        keeps) and, with ``inputs``, the digests of the files it read (`record_inputs`), each written atomically.
        A new run writes them before its first epoch; a continuation (``continued_from``: its first epoch) only at
        the end of its first epoch, after every check and that epoch have passed, so a continuation refused or
        stopped before then leaves the run as it was."""
        self.write_config(config, continued_from)
        if inputs is not None:
            self.record_inputs(inputs)
        self.write_environment(versions)
        self.write_metrics(history)

    # --- metrics -------------------------------------------------------------------------------------------------

    def read_metrics(self, up_to_epoch: int | None = None) -> list[dict]:
        """Its `METRICS` records up to ``up_to_epoch`` (`read_metrics`: checked, a torn last line dropped)."""
        return read_metrics(self.metrics, up_to_epoch)

    def append_metrics(self, record: dict) -> None:
        """Add an epoch's record to `METRICS`."""
        with open(self.metrics, "a") as log:
            log.write(json.dumps(record) + "\n")

    def write_metrics(self, records: list[dict]) -> None:
        """Replace `METRICS` by ``records`` (atomically)."""
        with atomic_write(self.metrics) as temporary:
            temporary.write_text("".join(json.dumps(record) + "\n" for record in records))

    # --- checkpoints ---------------------------------------------------------------------------------------------

    def read_resume_point(self) -> tuple[dict, dict]:
        """(tensors, training state) of `LAST`, checked (`warpsense.system.checkpoint.resume_state`); a one-line
        CheckpointError naming the file otherwise."""
        from warpsense.system.checkpoint import read_checkpoint, resume_state

        tensors, meta = read_checkpoint(self.last)
        return tensors, resume_state(self.last, tensors, meta)

    def trained_epochs(self) -> int:
        """How many epochs its resume point holds."""
        return self.read_resume_point()[1]["epoch"] + 1

    def checkpoint_state(self, checkpoint: Path) -> dict | None:
        """The training state in the header of ``checkpoint`` (`last` or `best`), read without its tensors
        (`warpsense.system.checkpoint.read_header`); None where it is absent or cannot be read."""
        from warpsense.system.checkpoint import read_header

        try:
            return read_header(checkpoint)["state"]
        except (OSError, ValueError):  # absent (FileNotFoundError), damaged (CheckpointError)
            return None

    def kept_best(self) -> float:
        """The score of the best checkpoint as it was written (its header's state.best_miou), -1 where it has none
        or it cannot be read. A run resumed from a resume point before that checkpoint's epoch (stopped between an
        epoch's best checkpoint and its checkpoint_last, or between resume points) replaces it only with a better
        epoch, never with a redone one that scored less."""
        value = (self.checkpoint_state(self.best) or {}).get("best_miou")
        finite = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        return float(value) if finite else -1.0

    def best_record(self) -> dict | None:
        """The metrics record of the best epoch, from the best checkpoint's readable copy (`best_copy`); None where
        there is none. A damaged copy raises (OSError, ValueError, KeyError or TypeError)."""
        path = self.best_copy
        return json.loads(path.read_text())["state"]["record"] if path.is_file() else None

    # --- the end of a run ----------------------------------------------------------------------------------------

    def write_evaluation(self, record: dict) -> None:
        """Write the final evaluation (`EVALUATION`, atomically): the run is finished."""
        write_json(self.evaluation, record)

    def supersede_final_files(self, start_epoch: int) -> None:
        """At the first epoch a continuation completes (`--extend`, or more epochs with --allow-config-change), move
        the earlier end's `EVALUATION` and plots aside (`superseded_name`), before the config and the checkpoint
        change: until the continuation's own end writes them again the run holds no evaluation, so it reads as
        unfinished (`warpsense study` resumes the cell instead of reporting the old end's scores beside a newer
        checkpoint) and no plot shows the old end as the current one. A continuation refused or stopped before this
        epoch completes moves nothing."""
        for path in [self.evaluation, *sorted(self.path.glob("*.png"))]:
            if path.is_file() and ".epoch" not in path.name:
                path.replace(self.path / superseded_name(path.name, start_epoch))

    # --- inputs, environment, lock -------------------------------------------------------------------------------

    def record_inputs(self, digests: dict[str, dict]) -> None:
        """Write `INPUTS` (atomically): the digests of the files the run read, taken when it started reading them."""
        write_json(self.inputs, {"files": digests})

    def read_inputs(self) -> dict[str, dict] | None:
        """The digests the run recorded (`record_inputs`), None for a run written before runs recorded them; a
        damaged record is a one-line ConfigError naming the file and field."""
        path = self.inputs
        if not path.is_file():
            return None
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError, RecursionError) as error:
            raise ConfigError(f"{path}: unreadable: {first_line(error)}") from None
        files = record.get("files") if isinstance(record, dict) else None
        if not isinstance(files, dict) or not all(
                isinstance(entry, dict) and isinstance(entry.get("sha256"), str) for entry in files.values()):
            raise ConfigError(f"{path}: files: expected an object of path -> {{key, sha256}}, got {files!r}")
        return files

    def write_environment(self, versions: dict) -> None:
        """Write `ENVIRONMENT` (atomically): what produced the run (`warpsense.files.environment`)."""
        write_json(self.environment, versions)

    def lock(self) -> RunLock:
        """The run's `RunLock` (not yet acquired)."""
        return RunLock(self.path)

    def remove_unfinished(self, created: Path | None) -> None:
        """Remove the folders a training created (``created``: the outermost, None where it created none) when the
        run holds no checkpoint yet (a config the model refuses, a missing dataset, Ctrl-C in the first epoch):
        nothing partial is left on disk, and nothing suggests a resume. A run with a best checkpoint but no resume
        point yet (stopped between an epoch's best checkpoint and its checkpoint_last, or before
        train.checkpoint_every's first) is kept: that model is the user's."""
        if created is None or self.holds_run():
            return
        shutil.rmtree(self.path, ignore_errors=True)
        for folder in self.path.parents:  # the output folders made for it, while empty (another run may use them now)
            if not folder.is_relative_to(created):
                break
            try:
                folder.rmdir()
            except OSError:
                break


# the files' names as module constants, for callers written before `RunDir` (warpsense.study)
LAST, BEST, METRICS, LOCK = RunDir.LAST, RunDir.BEST, RunDir.METRICS, RunDir.LOCK


def superseded_name(name: str, epochs: int) -> str:
    """Where a continuation moves a file of the run's earlier end: "evaluation.json" -> "evaluation.epoch<E>.json"
    (``epochs``: the epochs that end had trained), and where it keeps the earlier config (`RunDir.earlier_config`)."""
    stem, dot, suffix = name.partition(".")
    return f"{stem}.epoch{epochs}.{suffix}" if dot else f"{name}.epoch{epochs}"


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
    """Whether ``folder`` holds a run (`RunDir.holds_run`)."""
    return RunDir(folder).holds_run()


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
            if match and RunDir(entry).resumable():
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
    """The config a resumed run trains with: its own (`RunDir.saved_config`). A ``requested`` config that differs
    from it (other than `RELOCATABLE_KEYS`) is refused with the differing keys named, unless ``allow_change``; then it
    is used. A change of task (`task_changes`) is refused either way: that is a new run. An allowed change is printed
    (the keys, old -> new). Reads only; writes nothing."""
    saved = RunDir(run_dir).saved_config()
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
    """The records of a metrics log (`RunDir.METRICS`) up to ``up_to_epoch`` (None: all of them); a torn
    (unparsable) last line, left by a kill while it was written, is dropped. A torn line elsewhere, a line that is
    not a JSON object, an epoch that is not an integer >= 0 or a time (`METRIC_SECONDS`) that is not a finite number
    >= 0 is a one-line ValueError naming the file, line and field."""
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
        self.path = Path(run_dir) / RunDir.LOCK
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
