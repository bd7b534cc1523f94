"""The files a run reads besides its config and its images, by content: the folder dataset's class table, the split
lists, the lens file and the teacher checkpoint. A run records their SHA-256 in its directory (`RunDir.INPUTS`) when
it starts, and a continuation (`--resume`, `--resume-dir`, `--extend`) compares them before anything is written: a file
that kept its path but changed (a class table with two ids swapped) would train the later epochs on another task
than the earlier ones, and the config, which names only the path, cannot see it."""

from __future__ import annotations

import hashlib
from pathlib import Path

from warpsense.config import ConfigError
from warpsense.train.run_dir import RunDir

INPUTS = RunDir.INPUTS
"""A run directory's record of the files it read (`RunDir.INPUTS`), under the name callers before `RunDir` import."""

SPLIT_LIST_DATASETS = ("camvid", "folder")
"""Datasets whose splits are lists <data.root>/<split>.txt (`warpsense.data.datasets.read_split_lists`)."""


def input_files(config) -> dict[str, str]:
    """The files a run of ``config`` reads besides its config and its images: path (as the config names it, or as
    the dataset finds it under data.root) -> the config key that makes the run read it. Only files that exist: a
    missing one is refused by its own reader, with its own message."""
    from warpsense.data import HELDOUT_SPLIT, evaluation_splits
    from warpsense.data.datasets import split_parts
    from warpsense.optics.lens import LensFileError, lens_path

    data, files = config.data, {}
    if data.dataset == "folder" and data.classes_file:
        files[data.classes_file] = "data.classes_file"
    splits = dict.fromkeys([data.train_split, data.val_split, *evaluation_splits(data)])
    splits.pop(HELDOUT_SPLIT, None)  # a fold's judged frames come from the lists of the labelled splits
    root = Path(data.root)
    for split in splits:
        if data.dataset in SPLIT_LIST_DATASETS:
            for part in split_parts(split):
                files[str(root / f"{part}.txt")] = f"data.root ({data.dataset} split list)"
        elif data.dataset == "kitti360":  # warpsense.data.datasets.KITTI360's frame list
            listing = root / "data_2d_semantics" / "train" / f"2013_05_28_drive_{split}_frames.txt"
            files[str(listing)] = "data.root (kitti360 frame list)"
    if config.optics.enabled:
        try:
            files[str(lens_path(config.optics.lens))] = "optics.lens"
        except LensFileError:  # not a lens: the camera refuses it
            pass
    if config.loss.distill_weight > 0 and config.loss.teacher:
        files[config.loss.teacher] = "loss.teacher"
    return {path: key for path, key in files.items() if Path(path).is_file()}


def _digest(path: Path) -> str:
    """SHA-256 of a file's bytes, read in blocks (a teacher checkpoint is megabytes)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def input_digests(config) -> dict[str, dict]:
    """{path: {"key", "sha256"}} of every file of `input_files` (what `record_inputs` writes)."""
    return {path: {"key": key, "sha256": _digest(Path(path))} for path, key in input_files(config).items()}


def record_inputs(run_dir: Path, digests: dict[str, dict]) -> None:
    """Write the run's record of the files it read (`RunDir.record_inputs`), the digests taken when it started."""
    RunDir(run_dir).record_inputs(digests)


def read_inputs(run_dir: Path) -> dict[str, dict] | None:
    """The digests a run recorded (`RunDir.read_inputs`), None for a run written before runs recorded them."""
    return RunDir(run_dir).read_inputs()


def changed_input(run_dir: Path, config) -> str | None:
    """The first file the run of ``run_dir`` read (`read_inputs`) that a run of ``config`` reads again under the same
    path and whose content changed since, in words ("PATH (KEY): its content changed since RUN read it (sha256 ...
    -> ...)"); None where none did. A file ``config`` no longer reads (a key changed) is not compared."""
    recorded = read_inputs(run_dir)
    if not recorded:
        return None
    for path, key in input_files(config).items():
        if path not in recorded:
            continue
        now, then = _digest(Path(path)), recorded[path]["sha256"]
        if now != then:
            return (f"{path} ({key}): its content changed since {run_dir} read it (sha256 {then[:12]}... -> "
                    f"{now[:12]}...)")
    return None


def check_inputs(run_dir: Path, config) -> None:
    """Refuse to continue ``run_dir`` with ``config`` where a file the run read has other content now
    (`changed_input`): a one-line ConfigError naming the file, the key that names it and both digests; nothing is
    written. A changed key is the config's check (`warpsense.train.run_dir.resumed_config`), refused there where it
    is one of task."""
    changed = changed_input(run_dir, config)
    if changed:
        raise ConfigError(f"{changed}: the continued epochs would train on another task than the earlier ones, so it "
                          "is not continued and nothing in it changed; put the file back as it was, or train a new "
                          "run (without --resume/--resume-dir)")
