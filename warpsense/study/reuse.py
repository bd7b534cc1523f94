"""Reusing other studies' runs (`--reuse DIR`): a cell whose resolved config a finished run of another study
directory trained (identical but for where the run lives) is copied in instead of trained again."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from warpsense.study.plan import Cell, Plan, PlanError
from warpsense.study.study_dir import StudyDir, read_record
from warpsense.train.run_dir import RunDir

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
        if not StudyDir(study_dir).runs.is_dir():
            raise FileNotFoundError(f"--reuse {study_dir}: no runs/ folder (not a study directory)")


def finished_runs(study_dirs: list[Path]) -> dict[str, Path]:
    """The finished run directories of other studies (their runs with an evaluation), by `_training_key`; the
    first directory given wins where two hold the same training. A run's saved config is read as this version reads
    a config (`warpsense.config.config_from_dict`): a key added since takes its default, which is the behaviour the
    run had (a new key's default keeps the old behaviour), and a key since retired at the value of the behaviour that
    stayed is dropped; a run whose config this version cannot read (a key it does not know, a retired behaviour)
    matches no cell. A damaged config or evaluation (torn, not a JSON object) is a one-line PlanError naming
    it, before anything is written: which cell the run trained cannot be told, and a copied run would count as done
    with a record no report can read."""
    from warpsense.config import ConfigError, config_from_dict

    found: dict[str, Path] = {}
    check_reuse_dirs(study_dirs)
    for study_dir in study_dirs:
        for folder in sorted(StudyDir(study_dir).runs.iterdir()):
            run = RunDir(folder)
            if not (run.finished() and run.config.is_file()):
                continue
            try:
                config = config_from_dict(read_record(run.config, dict), str(run.config))
            except ConfigError as error:
                print(f"--reuse: {folder} not considered: {error}")
                continue
            read_record(run.evaluation, dict)
            try:
                run.read_inputs()  # damaged: named here, before anything is written
            except ConfigError as error:
                raise PlanError(str(error)) from None
            found.setdefault(_training_key(config.to_dict()), folder)
    return found


def reuse_cells(plan: Plan, out: Path, cells: list[Cell], finished: dict[str, Path]) -> dict[Cell, Path]:
    """Copy into the study directory ``out`` every not-yet-started cell whose resolved config one of the
    ``finished`` runs (`finished_runs`) trained, identical but for `REUSE_IGNORED`, so that a study can take its
    reference cells from an earlier one; returns the cells copied and where from. The copy is the whole run
    directory, written under a temporary name first. A run whose recorded inputs (`warpsense.train.inputs`: its class
    table, split lists, lens file, teacher) have changed since it trained is not copied: the cell trains on today's
    files."""
    from warpsense.train.inputs import changed_input

    reused = {}
    if not finished:  # no --reuse: no cell's config to resolve here
        return reused
    study = StudyDir(out)
    for cell in cells:
        target = study.run(cell).path
        if study.cell_state(cell) != "new" or target.exists():
            continue
        config = plan.config(cell, study.runs)
        source = finished.get(_training_key(config.to_dict()))
        if source is None:
            continue
        changed = changed_input(source, config)  # the same config, but a file it read has changed since
        if changed:
            print(f"--reuse: {source} not copied for {cell.id}: {changed}; the cell trains", flush=True)
            continue
        partial = target.with_name(target.name + ".reusing")
        shutil.rmtree(partial, ignore_errors=True)
        shutil.copytree(source, partial)
        partial.rename(target)
        reused[cell] = source
    return reused
