"""Running a study's cells: one ordinary run directory per cell under <out>/runs, resumable, going on past a failed
cell, in this process (CPU, or one cell) or on a local pool of worker processes over the GPUs (several per GPU).

A cell is finished when its run directory holds `warpsense.train.engine.EVALUATION` (written after the last epoch):
it is never trained again. A cell with a last checkpoint but no evaluation resumes from that checkpoint. A scheduler
of the user's (a Slurm job array, ...) runs the commands `--plan-only` prints; the report reads the same directory.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import json
import math
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Iterator
from pathlib import Path

from warpsense.errors import first_line
from warpsense.files import atomic_write, write_json
from warpsense.study.mps import mps_daemon
from warpsense.study.mps import wanted as mps_wanted
from warpsense.study.plan import Cell, Plan, PlanError

PLAN_RECORD = "plan.json"
"""The resolved plan, written in the study directory by its first run (the report reads it)."""

THROUGHPUT = "throughput.json"
"""What each `study run` invocation trained, appended: cells finished, seconds, cells per hour, GPUs, per-cell
concurrency and the GPUs' busy fraction (sampled from nvidia-smi while it ran; absent without nvidia-smi)."""


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


def step_pixels(plan: Plan) -> int:
    """The most pixels a training step of any of the plan's cells holds (batch x crop height x width)."""
    firsts = {(cell.camera, cell.light): cell for cell in reversed(plan.cells())}  # folds and seeds share a crop
    configs = (plan.config(cell, "runs") for cell in firsts.values())
    return max(c.data.batch_size * c.data.crop_height * c.data.crop_width for c in configs)


def cell_work(plan: Plan, cells: list[Cell]) -> dict[Cell, int]:
    """Each cell's training work, epochs x training frames x crop pixels: what the pool balances over its GPUs and
    hands out longest first (`_pool`). A fold's training frames are the other sequences' (163-406 of CamVid's, so
    its cells run 1.1-2.5x as long as each other). Every cell counts 1 where a training set cannot be built (the cells
    then go in plan order; the cell reports the error when it trains)."""
    from warpsense.data import build_training

    sizes = {}  # training frames by data config: folds and cameras share them
    work = {}
    for cell in cells:
        config = plan.config(cell, "runs")
        key = repr(config.data)
        if key not in sizes:
            try:
                sizes[key] = len(build_training(config.data, config.run.seed))
            except Exception:  # noqa: BLE001 - any cell's own error is its to report when it trains, not the order's
                return dict.fromkeys(cells, 1)
        work[cell] = config.train.epochs * sizes[key] * config.data.crop_height * config.data.crop_width
    return work


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


def read_record(path: Path, kind: type | None = None):
    """The JSON file ``path`` of a study directory (its plan, throughput, a cell's evaluation, a run's config, the
    Slurm jobs); where it cannot be read or parsed, or (with ``kind``, dict or list) holds another JSON type, a
    one-line PlanError naming it (json's own message names no file)."""
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, ValueError, RecursionError) as error:  # ValueError: JSONDecodeError, UnicodeDecodeError
        raise PlanError(f"{path}: unreadable: {first_line(error)}") from None
    if kind is not None and not isinstance(record, kind):
        expected = "a JSON object" if kind is dict else "a JSON list"
        raise PlanError(f"{path}: unreadable: expected {expected}, got {type(record).__name__}")
    return record


THROUGHPUT_FIELDS = {"cells_finished": int, "seconds": float, "cells_per_hour": float, "gpus": list, "per_gpu": int}
"""The fields of a `THROUGHPUT` entry that its line (`throughput_line`) reads, and their types."""


def read_throughput(path: Path) -> list[dict]:
    """The entries of a study directory's `THROUGHPUT` file (none where it is absent), each checked for the fields
    `throughput_line` reads: a one-line PlanError naming the file, entry and field otherwise."""
    path = Path(path)
    if not path.is_file():
        return []
    entries = read_record(path, list)
    for number, entry in enumerate(entries, start=1):
        if not isinstance(entry, dict):
            raise PlanError(f"{path}: entry {number}: expected a JSON object, got {type(entry).__name__}")
        for field, kind in THROUGHPUT_FIELDS.items():
            value = entry.get(field)
            if not (_finite_number(value) if kind is float else isinstance(value, kind) and not isinstance(value, bool)):
                expected = "a finite number" if kind is float else kind.__name__
                raise PlanError(f"{path}: entry {number}: {field}: expected {expected}, got {value!r}")
        busy = entry.get("gpu_busy_fraction")
        if busy is not None and not (isinstance(busy, list) and all(_finite_number(value) for value in busy)):
            raise PlanError(f"{path}: entry {number}: gpu_busy_fraction: expected null or a list of numbers, got "
                            f"{busy!r}")
    return entries


def _finite_number(value) -> bool:
    """Whether a JSON value is a finite number (not a bool, whose JSON is true / false)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def read_plan_record(study_dir: Path) -> dict:
    """The plan a study directory holds (`PLAN_RECORD`, as `record_plan` wrote it); a one-line PlanError naming the
    directory where it holds none, or the file where it is unreadable or not a plan."""
    study_dir = Path(study_dir)
    path = study_dir / PLAN_RECORD
    if not study_dir.is_dir():
        raise PlanError(f"{study_dir}: no such study directory")
    if not path.is_file():
        raise PlanError(f"{study_dir}: not a study directory (no {PLAN_RECORD}); run `warpsense study run PLAN "
                        f"--out {study_dir}` first")
    record = read_record(path)
    try:
        Plan.from_dict(record)
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise PlanError(f"{path}: not a study plan record ({type(error).__name__}: {error})") from None
    return record


def record_throughput(out: Path, finished: int, seconds: float, gpus: list[str] | None, per_gpu: int,
                      busy: list[float] | None, mps: bool = False) -> dict:
    """Append this invocation's throughput to <out>/`THROUGHPUT` and print it in one line."""
    entry = {"cells_finished": finished, "seconds": seconds, "cells_per_hour": finished * 3600 / max(seconds, 1e-9),
             "gpus": list(gpus or []), "per_gpu": per_gpu if gpus else 1, "gpu_busy_fraction": busy, "mps": mps}
    path = Path(out) / THROUGHPUT
    print(f"study: {throughput_line(entry)}", flush=True)
    try:
        history = read_throughput(path)
    except ValueError as error:  # the cells are trained: a damaged history costs this entry, not the study
        print(f"study: warning: {error}; this run's throughput is not recorded there", file=sys.stderr, flush=True)
        return entry
    write_json(path, history + [entry])
    return entry


def throughput_line(entry: dict) -> str:
    """One `THROUGHPUT` entry in words (the run's last line, and the report's)."""
    where = f"{len(entry['gpus'])} GPU(s) x {entry['per_gpu']}" if entry["gpus"] else "one process"
    where += " under MPS" if entry.get("mps") else ""
    busy = entry.get("gpu_busy_fraction")
    busy_text = f"; GPU busy {', '.join(f'{fraction:.0%}' for fraction in busy)}" if busy else ""
    return (f"{entry['cells_finished']} cell(s) in {entry['seconds']:.0f} s on {where}: "
            f"{entry['cells_per_hour']:.1f} cells/hour{busy_text}")


def run_dir(out: Path, cell: Cell) -> Path:
    return Path(out) / "runs" / cell.run_name


def evaluation_path(out: Path, cell: Cell) -> Path:
    """The cell's `warpsense.train.engine.EVALUATION` file (present once the cell is finished)."""
    from warpsense.train.engine import EVALUATION

    return run_dir(out, cell) / EVALUATION


def read_evaluation(out: Path, cell: Cell) -> dict:
    return read_record(evaluation_path(out, cell))


def failure_path(out: Path, cell: Cell) -> Path:
    """Where a local run records why ``cell`` failed (<out>/logs/<cell>.failed, one line), for `warpsense study
    status`; removed when the cell trains again."""
    return out / "logs" / f"{cell.run_name}.failed"


def record_failure(out: Path, cell: Cell, reason: str) -> None:
    """Record why ``cell`` failed (`failure_path`), best effort: a record that cannot be written (a full disk) must
    not stop the study, which has reported the failure already."""
    path = failure_path(out, cell)
    with contextlib.suppress(OSError):
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as temporary:
            temporary.write_text(reason.replace("\n", " ") + "\n")


def recorded_failure(out: Path, cell: Cell) -> str | None:
    """Why ``cell``'s last local run failed (`record_failure`), or None."""
    try:
        return failure_path(out, cell).read_text().strip() or None
    except OSError:
        return None


def cell_state(out: Path, cell: Cell) -> str:
    """"done" (evaluated), "partial" (a checkpoint to resume) or "new"."""
    from warpsense.train.run_dir import LAST

    if evaluation_path(out, cell).is_file():
        return "done"
    return "partial" if (run_dir(out, cell) / LAST).is_file() else "new"


def _run_command(plan: Plan, out: Path, *options: str) -> list[str]:
    """`warpsense study run` of ``plan`` into ``out`` with ``options`` and the plan's command-line overrides."""
    command = ["warpsense", "study", "run", plan.source, "--out", str(out), *options]
    for text in plan.overrides:
        command += ["--set", text]
    return command


def cell_command(plan: Plan, out: Path, cell: Cell, reuse: list[Path] | tuple = ()) -> list[str]:
    """The command that runs one cell (what `--plan-only` prints, for a scheduler), copying it in from ``reuse``
    (study directories) where one holds the same training, as the local run would."""
    return _run_command(plan, out, "--cell", cell.id, *(option for path in reuse for option in ("--reuse", str(path))))


def record_plan(plan: Plan, out: Path) -> None:
    """Write the plan into ``out`` (first run), or refuse a different plan for a study directory that has one."""
    out = Path(out)
    path = out / PLAN_RECORD
    record = {key: value for key, value in plan.to_dict().items() if key != "source"}
    if path.is_file():
        saved = read_plan_record(out)
        saved.pop("source", None)
        saved.setdefault("folds", "none")  # a plan recorded before studies had folds
        saved.setdefault("sequences", [])
        if saved != json.loads(json.dumps(record)):
            raise PlanError(f"{path}: this study directory holds another plan ({saved.get('name')!r} with other "
                            f"cameras, lights, seeds or overrides); use a new --out")
        return
    (out / "runs").mkdir(parents=True, exist_ok=True)  # shared by the cells' run folders
    write_json(path, {**record, "source": plan.source})


REUSE_IGNORED = (("run", "name"), ("run", "output_dir"))
"""Config fields that name where a run lives, not what it trained: two runs that differ only there are the same."""


def _training_key(config: dict) -> str:
    """A run's config as text, without `REUSE_IGNORED`: equal keys, equal training."""
    config = json.loads(json.dumps(config))
    for section, key in REUSE_IGNORED:
        config.get(section, {}).pop(key, None)
    return json.dumps(config, sort_keys=True)


def check_reuse_dirs(study_dirs) -> None:
    """Each of ``--reuse``'s directories is a study directory (holds runs/), else FileNotFoundError naming it."""
    for study_dir in study_dirs:
        if not (Path(study_dir) / "runs").is_dir():
            raise FileNotFoundError(f"--reuse {study_dir}: no runs/ folder (not a study directory)")


def finished_runs(study_dirs: list[Path]) -> dict[str, Path]:
    """The finished run directories of other studies (``<dir>/runs/*`` with an evaluation), by `_training_key`; the
    first directory given wins where two hold the same training. A run's saved config is read as this version reads
    a config (`warpsense.config.config_from_dict`): a key added since takes its default, which is the behaviour the
    run had (a new key's default keeps the old behaviour), and a key since retired at the value of the behaviour that
    stayed is dropped; a run whose config this version cannot read (a key it does not know, a retired behaviour)
    matches no cell. A damaged config.json or evaluation (torn, not a JSON object) is a one-line PlanError naming
    it, before anything is written: which cell the run trained cannot be told, and a copied run would count as done
    with a record no report can read."""
    from warpsense.config import ConfigError, config_from_dict
    from warpsense.train.engine import EVALUATION
    from warpsense.train.inputs import read_inputs

    found: dict[str, Path] = {}
    check_reuse_dirs(study_dirs)
    for study_dir in study_dirs:
        for run in sorted((Path(study_dir) / "runs").iterdir()):
            saved = run / "config.json"
            if not ((run / EVALUATION).is_file() and saved.is_file()):
                continue
            try:
                config = config_from_dict(read_record(saved, dict), str(saved))
            except ConfigError as error:
                print(f"--reuse: {run} not considered: {error}")
                continue
            read_record(run / EVALUATION, dict)
            try:
                read_inputs(run)  # damaged: named here, before anything is written
            except ConfigError as error:
                raise PlanError(str(error)) from None
            found.setdefault(_training_key(config.to_dict()), run)
    return found


def reuse_cells(plan: Plan, out: Path, cells: list[Cell], finished: dict[str, Path]) -> dict[Cell, Path]:
    """Copy into <out>/runs every not-yet-started cell whose resolved config one of the ``finished`` runs
    (`finished_runs`) trained, identical but for `REUSE_IGNORED`, so that a study can take its reference cells from
    an earlier one; returns the cells copied and where from. The copy is the whole run directory, written under a
    temporary name first. A run whose recorded inputs (`warpsense.train.inputs`: its class table, split lists,
    lens file, teacher) have changed since it trained is not copied: the cell trains on today's files."""
    from warpsense.train.inputs import changed_input

    reused = {}
    if not finished:  # no --reuse: no cell's config to resolve here
        return reused
    for cell in cells:
        if cell_state(out, cell) != "new" or run_dir(out, cell).exists():
            continue
        config = plan.config(cell, Path(out) / "runs")
        source = finished.get(_training_key(config.to_dict()))
        if source is None:
            continue
        changed = changed_input(source, config)  # the same config, but a file it read has changed since
        if changed:
            print(f"--reuse: {source} not copied for {cell.id}: {changed}; the cell trains", flush=True)
            continue
        target = run_dir(out, cell)
        partial = target.with_name(target.name + ".reusing")
        shutil.rmtree(partial, ignore_errors=True)
        shutil.copytree(source, partial)
        partial.rename(target)
        reused[cell] = source
    return reused


def train_cell(plan: Plan, out: Path, cell: Cell, progress: bool = False) -> dict:
    """Train (or resume) and evaluate one cell in this process; returns its evaluation record."""
    from warpsense.train.engine import train
    from warpsense.train.run_dir import holds_run, set_aside

    state = cell_state(out, cell)
    if state != "done":
        config = plan.config(cell, Path(out) / "runs")
        if state == "new" and holds_run(run_dir(out, cell)):  # stopped before its first resume point: its best kept
            kept = set_aside(run_dir(out, cell))
            print(f"{cell.id}: an attempt stopped before its first resume point left a best checkpoint: kept in "
                  f"{kept}; the cell trains from the start", flush=True)
        train(config, resume=run_dir(out, cell) if state == "partial" else False, progress=progress)
    return read_evaluation(out, cell)


def score_line(record: dict) -> str:
    """A cell's evaluation in words: "val mIoU 0.7123, test mIoU ..." (its splits in order)."""
    return ", ".join(f"{split} mIoU {metrics['miou']:.4f}" for split, metrics in record["splits"].items())


def run_cells(plan: Plan, out: Path, cells: list[Cell] | None = None, gpus: list[str] | None = None,
              per_gpu: int = 1, progress: bool = False, record: bool = True,
              sample_gpus: list[str] | None = None, reuse: list[Path] | None = None, mps: str = "auto") -> int:
    """Run the cells not finished yet; a progress line per cell; returns the exit code (0 all finished, 1 some
    failed, 130 interrupted).

    Args:
        cells: the cells to run (default: all of the plan).
        progress: each cell's progress bars: on this process's output where the cells run here, in each cell's log
            with a pool (several workers' bars would overwrite each other on one terminal).
        gpus: device ids for a local pool of worker processes (indices into CUDA_VISIBLE_DEVICES: `cuda_device`),
            ``per_gpu`` on each, each training its cells one after another; None or empty: the cells run one after
            another here.
        record: append this invocation's throughput to <out>/`THROUGHPUT` (a one-cell invocation does not).
        sample_gpus: GPU ids whose busy fraction is sampled meanwhile (default: ``gpus``; the command passes the
            visible GPUs also when the cells run in this process on one GPU).
        reuse: other study directories whose finished runs are copied in for the cells they already trained
            (`reuse_cells`).
        mps: run the pool's workers under a CUDA MPS daemon of its own (`warpsense.study.mps`): "auto" (with
            ``per_gpu`` > 1 where the control program is on the PATH), "on" or "off".
    """
    out = Path(out)
    cells = plan.cells() if cells is None else cells
    shared = bool(gpus) and mps_wanted(mps, per_gpu)  # a bad mode, or "on" without MPS, before anything is written
    finished = finished_runs(list(reuse or []))  # a bad directory is refused before anything is written
    record_plan(plan, out)
    reused = reuse_cells(plan, out, cells, finished)
    pending = [cell for cell in cells if cell_state(out, cell) != "done"]
    total = len(cells)
    for index, cell in enumerate(cells, start=1):
        if cell in reused:
            print(f"[{index}/{total}] {cell.id}: the same training as {reused[cell]}, copied in", flush=True)
        elif cell not in pending:
            print(f"[{index}/{total}] {cell.id}: finished earlier, skipped", flush=True)
    if not pending:
        return 0
    numbering = {cell: cells.index(cell) + 1 for cell in pending}
    started = time.perf_counter()
    sampled = list(sample_gpus if sample_gpus is not None else gpus or []) if record else []
    with BusySampler(sampled) as sampler:
        if gpus:
            if progress:
                print(f"study: --progress: each cell's progress bars go to its log ({out / 'logs'}/<cell>.log)",
                      flush=True)
            with mps_daemon(shared) as environment:
                failed = _pool(plan, out, pending, numbering, total, gpus, per_gpu, environment, progress)
        else:
            failed = _in_process(plan, out, pending, numbering, total, progress)
    if record:
        finished = sum(cell_state(out, cell) == "done" for cell in pending)
        record_throughput(out, finished, time.perf_counter() - started, gpus, per_gpu, sampler.fractions(), shared)
    if failed is None:
        return 130
    if failed:
        resumed = [str(run_dir(out, cell)) for cell in failed if cell_state(out, cell) == "partial"]
        again = (f" A retry resumes {', '.join(resumed)} from its last checkpoint: if it fails the same way, delete "
                 "that folder to train the cell from the start.") if resumed else ""
        print(f"study: {len(failed)} of {total} cells failed: {', '.join(c.id for c in failed)}; the others are "
              f"done. Run the same command again to retry them.{again}", file=sys.stderr)
        return 1
    return 0


def _in_process(plan, out, pending, numbering, total, progress) -> list[Cell] | None:
    """Cells one after another here; the failed ones, or None after Ctrl-C."""
    from warpsense.train.engine import TrainingInterrupted

    failed = []
    for cell in pending:
        started = time.perf_counter()
        prefix = f"[{numbering[cell]}/{total}] {cell.id}"
        print(f"{prefix}: {'resuming' if cell_state(out, cell) == 'partial' else 'training'}", flush=True)
        failure_path(out, cell).unlink(missing_ok=True)
        try:
            record = train_cell(plan, out, cell, progress)
        except TrainingInterrupted:
            print(f"{prefix}: interrupted; run the same command again to resume it (finished cells are kept)",
                  file=sys.stderr)
            return None
        except Exception as error:  # noqa: BLE001 - a failed cell is reported and the study goes on
            failed.append(cell)
            reason = f"{type(error).__name__}: {first_line(error)}"
            record_failure(out, cell, reason)
            print(f"{prefix}: FAILED: {reason}", file=sys.stderr, flush=True)
            continue
        print(f"{prefix}: done in {time.perf_counter() - started:.0f} s, {score_line(record)}", flush=True)
    return failed


def worker_command(plan: Plan, out: Path, progress: bool = False) -> list[str]:
    """The command of one of the local pool's worker processes (`cell_worker`), with ``progress`` bars."""
    return [sys.executable, "-m", *_run_command(plan, out, "--worker", *(["--progress"] if progress else []))]


@contextlib.contextmanager
def _output_to(handle) -> Iterator[None]:
    """Python's stdout and stderr, and file descriptors 1 and 2 (native libraries' output), into ``handle``, then
    back."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    os.dup2(handle.fileno(), 1)
    os.dup2(handle.fileno(), 2)
    try:
        with contextlib.redirect_stdout(handle), contextlib.redirect_stderr(handle):
            yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])


def cell_worker(plan: Plan, out: Path, progress: bool = False) -> int:
    """One process of the local pool: trains the cells whose ids arrive on stdin (one a line), one after another in
    this process, each one's output (with ``progress``: its progress bars too) appended to <out>/logs/<cell>.log,
    and answers each on stdout with one line, ``done <id>`` or ``failed <id> <reason>``. One process per GPU slot
    rather than one per cell: the interpreter, CUDA context, Warp modules and the data on the device are paid once
    per worker (2 x H100, docs/history.md: a process per 10-epoch cell took 60 s against 18 s in one process).
    Returns 0 at the end of stdin, 130 on Ctrl-C."""
    from warpsense.train.engine import TrainingInterrupted

    out = Path(out)
    answers = os.fdopen(os.dup(1), "w", buffering=1)
    sys.stdout.flush()
    os.dup2(2, 1)  # anything printed between cells goes to stderr: stdout carries the answers alone
    for line in sys.stdin:
        cell = plan.cell(line.strip())
        with open(out / "logs" / f"{cell.run_name}.log", "a", buffering=1) as handle, _output_to(handle):
            try:
                print(f"{cell.id}: {'resuming' if cell_state(out, cell) == 'partial' else 'training'} in worker "
                      f"process {os.getpid()}", flush=True)
                train_cell(plan, out, cell, progress)
                answer = f"done {cell.id}"
            except TrainingInterrupted:
                return 130
            except Exception as error:  # noqa: BLE001 - a failed cell is reported and the worker goes on
                traceback.print_exc()
                answer = f"failed {cell.id} {type(error).__name__}: {first_line(error)}"
        answers.write(answer + "\n")
    return 0


def worker_environment(gpu: str, workers: int, environ=None, cores: int | None = None,
                       extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of a pool worker: its GPU alone (``CUDA_VISIBLE_DEVICES``) and its share of the CPU's cores
    as OpenMP threads (``OMP_NUM_THREADS`` = cores // workers, at least 1; kept where the caller set it), as
    torchrun limits its ranks: every worker running an OpenMP pool of all the cores oversubscribes the CPU, and on
    2 H100s with 16 cores each cell's set-up (the data onto the GPU, its copy-paste classes) took 5-8 s instead of
    1 s (docs/history.md).

    The GPU is ``gpu``'s entry of the caller's CUDA_VISIBLE_DEVICES (`cuda_device`). Under the pool's MPS daemon
    (``extra`` names its pipe directory) it stays the bare id: the daemon, started with the caller's environment,
    renumbers the devices it sees from 0, and a client naming one by its outer index fails (NVIDIA's MPS guide,
    CUDA_VISIBLE_DEVICES)."""
    environment = dict(os.environ if environ is None else environ)
    device = cuda_device(gpu, environment)  # an id past the visible devices is refused either way
    environment["CUDA_VISIBLE_DEVICES"] = gpu if "CUDA_MPS_PIPE_DIRECTORY" in (extra or {}) else device
    cores = cores or os.cpu_count() or 1
    environment.setdefault("OMP_NUM_THREADS", str(max(1, cores // max(workers, 1))))
    environment.update(extra or {})  # the pool's MPS daemon (warpsense.study.mps)
    return environment


def _pool(plan, out, pending, numbering, total, gpus, per_gpu, environment=None, progress=False) -> list[Cell] | None:
    """Cells on ``per_gpu`` worker processes per GPU (`cell_worker`), the longest first (`cell_work`; equal ones in
    plan order), each slot taking the next pending cell when it is free and no GPU with a free slot runs less work
    than its own (fewer cells than slots spread over the GPUs instead of filling the first, and a GPU's cells under
    MPS share it, so its load is the sum of their work); each cell writes its output to <out>/logs/<cell>.log. A
    worker that dies fails its cell and is replaced for the next. The failed cells, or None after Ctrl-C (every
    worker is interrupted; a cell's last checkpoint resumes it).

    Why longest first by work: the 12 cells of 3 CamVid folds x 4 seeds on 4 GPUs x 3 slots went out in plan order,
    and one GPU took the three longest cells (406 training frames each) while two others finished at 150-200 s of the
    study's 297 (docs/benchmarks.md, studies per GPU-hour)."""
    work = cell_work(plan, pending)
    todo = collections.deque(sorted(pending, key=lambda cell: -work[cell]))  # a stable sort: ties in plan order
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    failed, running, lock, stopping = [], set(), threading.Lock(), threading.Event()
    turn = threading.Condition()  # guards `todo` and `active`
    active = dict.fromkeys(gpus, 0)  # cells running on each GPU
    load = dict.fromkeys(gpus, 0)  # their work

    def take(gpu: str) -> Cell | None:
        """The next pending cell for a slot of ``gpu`` once no GPU with a free slot runs less work; None when none
        is left."""
        with turn:
            while todo and not stopping.is_set() and any(active[other] < per_gpu and load[other] < load[gpu]
                                                         for other in gpus):
                turn.wait(timeout=1.0)
            if not todo or stopping.is_set():
                return None
            cell = todo.popleft()
            active[gpu] += 1
            load[gpu] += work[cell]
            turn.notify_all()  # a slot of another GPU may wait for this one to take its share
            return cell

    def release(gpu: str, cell: Cell) -> None:
        with turn:
            active[gpu] -= 1
            load[gpu] -= work[cell]
            turn.notify_all()

    def start(gpu: str) -> subprocess.Popen:
        process = subprocess.Popen(worker_command(plan, out, progress), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                   text=True, bufsize=1, env=worker_environment(gpu, len(gpus) * per_gpu,
                                                                          extra=environment))
        with lock:
            running.add(process)
        return process

    def stop(process: subprocess.Popen) -> None:
        with contextlib.suppress(OSError):
            process.stdin.close()
        process.wait()
        with lock:
            running.discard(process)

    def slot(gpu: str) -> None:
        process = None
        while (cell := take(gpu)) is not None:
            try:
                process = train(gpu, cell, process)
            except Exception as error:  # e.g. the worker cannot start: the cell fails, the slot goes on
                if process is not None:
                    stop(process)
                process = None
                fail(cell, first_line(error))
            finally:
                release(gpu, cell)
        if process is not None and not stopping.is_set():
            stop(process)

    def train(gpu: str, cell: Cell, process: subprocess.Popen | None) -> subprocess.Popen | None:
        """Train ``cell`` on the slot's worker ``process`` (a fresh one when None); the worker for its next cell."""
        prefix = f"[{numbering[cell]}/{total}] {cell.id}"
        log = logs / f"{cell.run_name}.log"
        print(f"{prefix}: started on GPU {gpu} (log {log})", flush=True)
        failure_path(out, cell).unlink(missing_ok=True)
        started = time.perf_counter()
        process = process or start(gpu)
        try:
            process.stdin.write(cell.id + "\n")
            process.stdin.flush()
            answer = process.stdout.readline().strip()
        except OSError:
            answer = ""
        if stopping.is_set():
            return process
        if answer == f"done {cell.id}" and cell_state(out, cell) == "done":
            record = read_evaluation(out, cell)
            print(f"{prefix}: done in {time.perf_counter() - started:.0f} s on GPU {gpu}, {score_line(record)}",
                  flush=True)
            return process
        if not answer:  # the worker died: its exit status, and a fresh worker for the next cell
            stop(process)
            answer = f"worker exit {process.returncode}"
            process = None
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()] \
            if log.is_file() else []
        reason = answer.removeprefix(f"failed {cell.id} ")  # the worker's own line: "Type: message"
        detail = lines[-1] if lines else "no output"
        fail(cell, reason, None if detail == reason else detail)
        return process

    def fail(cell: Cell, why: str, detail: str | None = None) -> None:
        """Record ``cell`` as failed and say so: "FAILED (why)", then ": detail" where given."""
        with lock:
            failed.append(cell)
        more = f": {detail}" if detail else ""
        record_failure(out, cell, why + more)
        print(f"[{numbering[cell]}/{total}] {cell.id}: FAILED ({why}){more}", file=sys.stderr, flush=True)

    threads = [threading.Thread(target=slot, args=(gpu,), daemon=True) for gpu in gpus for _ in range(per_gpu)]
    for thread in threads:
        thread.start()
    try:
        for thread in threads:
            while thread.is_alive():
                thread.join(timeout=1.0)
    except KeyboardInterrupt:
        stopping.set()
        with lock:
            processes = list(running)
        for process in processes:  # each cell stops at once and keeps its last epoch's checkpoint
            process.send_signal(signal.SIGINT)
        for process in processes:
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
        print("study: interrupted; run the same command again to resume (finished cells are kept)", file=sys.stderr)
        return None
    return sorted(failed, key=lambda cell: numbering[cell])


def plan_commands(plan: Plan, out: Path, reuse: list[Path] | tuple = (), cells: list[Cell] | None = None) -> list[str]:
    """One shell command per cell (default: every cell of the plan), for a scheduler of the user's (with
    ``reuse``'s --reuse options)."""
    return [shlex.join(cell_command(plan, out, cell, reuse)) for cell in (plan.cells() if cells is None else cells)]


def check_runnable(plan: Plan, cells: list[Cell], local: bool = True) -> None:
    """Refuse, before anything is written, cells this machine cannot train (``local``: they run here): a config that
    asks for a device it does not have (run.device = "cuda" without CUDA) or a CUDA-only feature on the CPU
    (train.cuda_graph), in one line naming the key and the cells (each distinct camera and light checked once).
    A study whose cells all failed at once would have written its plan and refused the corrected command."""
    from warpsense.system import resolve_device

    if not local:
        return
    checked = set()
    for cell in cells:
        if (cell.camera, cell.light) in checked:
            continue
        checked.add((cell.camera, cell.light))
        config = plan.config(cell, "runs")
        try:
            device = resolve_device(config.run.device)
        except ValueError as error:
            raise PlanError(f"{plan.source}: cell {cell.id}: run.device = {config.run.device!r}: {error}") from None
        if config.train.cuda_graph and device.type != "cuda":
            raise PlanError(f"{plan.source}: cell {cell.id}: train.cuda_graph needs a CUDA device and this machine "
                            f"trains on {device.type} (--set train.cuda_graph=false)")
