"""A study plan file's tables checked one by one: each table's keys and their types, names that can name a cell,
a ``[[sweep]]``'s grid and its cameras, ``study.sequential``'s rule and its seeds, the ``[[search]]`` table, and the
command line's ``study.KEY=VALUE`` and ``search.KEY=VALUE`` entries applied to them. Every error is a one-line
`PlanError` naming the plan file and key; `warpsense.study.plan.load_plan` puts the tables together."""

from __future__ import annotations

import dataclasses
import itertools
import json

from warpsense.config import Config, ConfigError, flatten_keys, parse_override
from warpsense.study.keys import value_label
from warpsense.study.plan_model import PlanError, SweepSpec, plain_name
from warpsense.study.search_space import SearchError, SearchSpec, parse_search
from warpsense.study.sequential import SequentialRule, check_rule

STUDY_KEYS = {"name": str, "base": str, "set": list, "seeds": list, "reference": str, "folds": str, "sequences": list,
              "blocks": int, "block_buffer": int, "sequential": dict}


CAMERA_KEYS = {"name": str, "preset": str, "set": list, "seed_offset": int}
SWEEP_KEYS = {"name": str, "preset": str, "set": list, "grid": dict, "labels": dict}
LIGHT_KEYS = {"name": str, "full_well_electrons": (int, float), "read_electrons": (int, float), "bits": int,
              "cameras": list, "scene": str, "analog_gain": (int, float), "set": list}


def study_overrides(study: dict, overrides, source: str, table: str = "study") -> dict:
    """The [study] table (or, with ``table`` "search", a [[search]] table) with the command line's
    ``study.KEY=VALUE`` (``search.KEY=VALUE``) entries applied."""
    study = dict(study)
    for text in overrides:
        if text.split("=", 1)[0].strip().startswith(f"{table}."):
            try:
                study.update(parse_override(text)[table])
            except ConfigError as error:
                raise PlanError(f"{source}: {error}") from None
    return study


def check_table(data: dict, keys: dict, where: str, required: tuple[str, ...]) -> dict:
    """``data`` (a table of the plan at ``where``) with only ``keys`` (key -> its type or types), the ``required``
    ones present, each of its type (a boolean is no number); else a PlanError naming the key."""
    for key in data:
        if key not in keys:
            raise PlanError(f"{where}.{key}: unknown key; valid keys: {', '.join(keys)}")
    for key in required:
        if key not in data:
            raise PlanError(f"{where}.{key}: missing")
    for key, value in data.items():
        expected = keys[key]
        if isinstance(value, bool) or not isinstance(value, expected):
            kinds = " or ".join(t.__name__ for t in (expected if isinstance(expected, tuple) else (expected,)))
            raise PlanError(f"{where}.{key}: expected {kinds}, got {type(value).__name__} {value!r}")
    return data


def string_list(values: list, where: str) -> tuple[str, ...]:
    """A ``set`` list of override strings as a tuple; a PlanError at ``where`` for anything else in it."""
    if not all(isinstance(value, str) for value in values):
        raise PlanError(f"{where}: expected a list of \"section.key=value\" strings")
    return tuple(values)


def optional_float(value) -> float | None:
    """A number of the plan as a float (None stays None: the key was not given)."""
    return None if value is None else float(value)


def check_names(items: list, where: str, other: str = "") -> None:
    """Every item's ``name`` is a plain name (`plain_name`) and none repeats; ``other`` says where else a name
    may come from."""
    seen = set()
    for item in items:
        name = item["name"]
        if not name or not plain_name(name):
            raise PlanError(f"{where}.name: {name!r} must be a plain name (no '/', '.' or spaces at the ends)")
        if name in seen:
            raise PlanError(f"{where}.name: duplicate name {name!r}" + (f" (also {other})" if other else ""))
        seen.add(name)


def _config_key(key: str, where: str) -> None:
    """``key`` ("section.field") names a field of the config, else a PlanError at ``where``."""
    section, _, name = key.partition(".")
    part = getattr(Config(), section, None) if section in {f.name for f in dataclasses.fields(Config)} else None
    if part is None or name not in {f.name for f in dataclasses.fields(part)}:
        raise PlanError(f"{where}: {key!r} is not a config key (section.key, e.g. optics.f_number)")


def sweep_spec(table: dict, where: str) -> SweepSpec:
    """A checked ``[[sweep]]`` table with its points (the grid's Cartesian product, first key slowest)."""
    table = check_table(table, SWEEP_KEYS, where, ("name", "grid"))
    grid, labels = flatten_keys(table["grid"]), flatten_keys(table.get("labels", {}))
    if not grid:
        raise PlanError(f"{where}.grid: give at least one config key and its values")
    for key, values in grid.items():
        _config_key(key, f"{where}.grid.{key}")
        if not isinstance(values, list) or not values:
            raise PlanError(f"{where}.grid.{key}: expected a non-empty list of values, got {values!r}")
        distinct = len(set(map(repr, values))) == len(values)
        if not all(isinstance(v, (str, int, float, bool)) for v in values) or not distinct:
            raise PlanError(f"{where}.grid.{key}: expected distinct numbers, strings or booleans, got {values!r}")
    for key, label in labels.items():
        if key not in grid:
            raise PlanError(f"{where}.labels.{key}: not a key of the grid; keys: {', '.join(grid)}")
        if not isinstance(label, str) or not plain_name(label):
            raise PlanError(f"{where}.labels.{key}: expected a plain string (no '/', '.' or spaces), got {label!r}")
    names = tuple(labels.get(key, key.rsplit(".", 1)[-1]) for key in grid)
    points, seen = [], {}
    for values in itertools.product(*grid.values()):
        camera = "_".join([table["name"], *(f"{label}{value_label(v)}" for label, v in zip(names, values))])
        if camera in seen:
            raise PlanError(f"{where}.labels: points {seen[camera]!r} and {values!r} are both named {camera!r}; give "
                            "the grid's keys distinct labels or its values distinct names")
        seen[camera] = values
        points.append((camera, tuple(values)))
    return SweepSpec(table["name"], table.get("preset", ""), string_list(table.get("set", []), f"{where}.set"),
                     tuple(grid), names, tuple(tuple(v) for v in grid.values()), tuple(points))


def point_overrides(sweep: SweepSpec, values: tuple) -> list[str]:
    """A grid point's overrides: ``key=value`` per swept key (after the sweep's ``set``)."""
    return [f"{key}={json.dumps(value)}" for key, value in zip(sweep.parameters, values)]


def sequential_rule(study: dict, source: str, pairs_per_seed: int) -> SequentialRule | None:
    """The plan's ``study.sequential`` rule checked (None without one), its first look holding ``pairs_per_seed`` x
    min_seeds pairs; a PlanError naming the key otherwise."""
    if "sequential" not in study:
        return None
    try:
        return check_rule(study["sequential"], f"{source}: study.sequential", pairs_per_seed)
    except ValueError as error:
        raise PlanError(str(error)) from None


def sequential_seeds(seeds: list, rule: SequentialRule, source: str) -> list:
    """A sequential plan's seeds in the order they are added: ``seeds``, then the next integers not among them, up
    to max_seeds; a PlanError where ``seeds`` lists more."""
    if len(seeds) > rule.max_seeds:
        raise PlanError(f"{source}: study.seeds: {len(seeds)} seeds listed, study.sequential.max_seeds is "
                        f"{rule.max_seeds}: list at most that many (the rest follow the last)")
    seeds, candidate = list(seeds), max(seeds) + 1
    while len(seeds) < rule.max_seeds:
        if candidate not in seeds:
            seeds.append(candidate)
        candidate += 1
    return seeds


def search_spec(tables, source: str, lights: list[str], cameras: list[str], overrides) -> SearchSpec | None:
    """The plan's ``[[search]]`` (at most one), with the command line's ``search.KEY=VALUE`` entries, checked; a
    PlanError naming the key otherwise."""
    if not isinstance(tables, list) or not all(isinstance(table, dict) for table in tables):
        raise PlanError(f"{source}: search: expected a [[search]] table")
    if len(tables) > 1:
        raise PlanError(f"{source}: search: one [[search]] table per plan, got {len(tables)}")
    if not tables:
        return None
    try:
        return parse_search(study_overrides(tables[0], overrides, source, "search"), f"{source}: search[0]", lights,
                            cameras)
    except SearchError as error:
        raise PlanError(str(error)) from None


def seed_offset(camera: dict, source: str) -> int:
    """A ``[[camera]]``'s ``seed_offset`` (0 where not given); a PlanError for a negative one."""
    offset = camera.get("seed_offset", 0)
    if offset < 0:
        raise PlanError(f"{source}: camera {camera['name']}.seed_offset: expected an integer >= 0, got {offset}")
    return offset
