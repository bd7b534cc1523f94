"""What a plan says is what runs: a config key that two of a cell's plan tables set to different values is refused.

A cell's config applies, in order, the base, the camera's preset, the study's ``set``, the camera's ``set`` (for a
sweep's point: the sweep's ``set``, then the point's grid values), the light's keys and ``set``, the fold, the seed,
then the command line's ``--set``. Each later table would silently override an earlier one, so a light that sets a
key a sweep sweeps, or a study ``set`` that overrides a camera's preset, would train something other than the plan
file and the report's labels say. Only the base is meant to be overridden (it is every cell's shared recipe), and the
command line (the user's explicit change of every cell, recorded in the study's plan.json). The keys the study sets
per cell (run.seed, run.name, run.output_dir and the fold's data keys) are set by no table.
"""

from __future__ import annotations

import json

from warpsense.config import Config, ConfigError, flatten_keys, load_config, parse_override

PER_CELL_KEYS = ("run.seed", "run.name", "run.output_dir", "data.holdout_sequence", "data.holdout_block",
                 "data.holdout_blocks", "data.block_buffer")
"""Keys the study sets for each cell (`warpsense.study.plan.Plan.config`): a table that set them would be
overridden."""


def _assignments(texts, where: str) -> dict[str, tuple[object, str]]:
    """``section.key=value`` overrides as {key: (value, where)}; later texts of one table win, as they do in
    `load_config`."""
    keys = {}
    for text in texts:
        for section, values in parse_override(text).items():
            for key, value in values.items():
                keys[f"{section}.{key}"] = (value, where)
    return keys


def _flat(config: Config) -> dict:
    """A config as {"section.key": value}."""
    return {f"{section}.{key}": value for section, values in config.to_dict().items()
            for key, value in flatten_keys(values).items()}


def preset_keys(base: str, preset: str, cache: dict) -> dict[str, object]:
    """The keys a camera's preset sets beyond the study's base: those whose value the preset changes (but
    `PER_CELL_KEYS`: a preset names its own runs for `warpsense train`, which a study's cell renames)."""
    if (base, preset) not in cache:
        start = _flat(load_config([base] if base else None))
        changed = _flat(load_config([file for file in (base, preset) if file]))
        cache[base, preset] = {key: value for key, value in changed.items()
                               if start.get(key) != value and key not in PER_CELL_KEYS}  # a preset's own run name
    return cache[base, preset]


def _same(a, b) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True) or (
        isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool)
        and not isinstance(b, bool) and float(a) == float(b))


def check_conflicts(plan, error: type[Exception] = ValueError) -> None:
    """Refuse a plan (a `warpsense.study.plan.Plan`) in which two tables set one config key of a cell to different
    values, or a table sets a key the study sets per cell (`PER_CELL_KEYS`): an ``error`` (the plan's `PlanError`)
    naming the plan file, the key, both tables and both values."""
    PlanError = error  # noqa: N806 - the caller's error class, raised as the plan's own

    sweeps = {camera: (sweep, values) for sweep in plan.sweeps for camera, values in sweep.points}
    cache: dict = {}
    try:
        study = _assignments(plan.set, "[study].set")
        for camera in plan.cameras:
            tables = []  # in the order Plan.config applies them
            if camera.preset:
                tables.append({key: (value, f"camera {camera.name!r}'s preset {camera.preset!r}")
                               for key, value in preset_keys(plan.base, camera.preset, cache).items()})
            tables.append(study)
            if camera.name in sweeps:
                sweep, values = sweeps[camera.name]
                tables.append(_assignments(sweep.set, f"sweep {sweep.name!r}'s set"))
                tables.append({key: (value, f"sweep {sweep.name!r}'s grid") for key, value in
                               zip(sweep.parameters, values)})
            else:
                tables.append(_assignments(camera.set, f"camera {camera.name!r}'s set"))
            for light in plan.lights:
                if light.cameras and camera.name not in light.cameras:
                    continue
                _check_cell(tables + [_assignments(light.overrides(), f"light {light.name!r}")], plan.source,
                            PlanError)
    except ConfigError as error:
        raise PlanError(f"{plan.source}: {error}") from None


def _check_cell(tables: list[dict], source: str, error) -> None:
    seen: dict[str, tuple[object, str]] = {}
    for table in tables:
        for key, (value, where) in table.items():
            if key in PER_CELL_KEYS:
                raise error(f"{source}: {where} sets {key}, which the study sets for each cell (its seed, name, "
                            f"folder or fold); leave it out")
            if key in seen and not _same(seen[key][0], value) and seen[key][1] != where:
                raise error(f"{source}: {key} is {json.dumps(seen[key][0])} in {seen[key][1]} and "
                            f"{json.dumps(value)} in {where}: the later table would override the earlier one, so the "
                            f"cells would not train what the plan says; set it in one table")
            seen[key] = (value, where)

