"""A plan's ``[[search]]`` table: the design space a Bayesian search proposes cameras in, and how a proposed design
becomes a camera of the plan.

    [[search]]
    name = "search"                 # the designs' camera name prefix: search_f1p76_t14p4 (values as a sweep's)
    preset = ""                     # as a camera's (optional)
    set = []                        # overrides of every design (optional)
    bounds = { "optics.f_number" = [1.4, 8.0], "optics.exposure_ms" = [1.0, 30.0] }  # float config key -> [low, high]
    log = { "optics.f_number" = true, "optics.exposure_ms" = true }   # searched on a log scale (default false)
    labels = { "optics.f_number" = "f", "optics.exposure_ms" = "t" }  # name labels (default: the key's last part)
    digits = 3                      # significant digits of a proposed value (the design's name and config)
    budget = 24                     # cells the search may train (its designs'; the plan's cameras are not counted)
    seeds = 1                       # seeds per design: the first of study.seeds
    light = "night"                 # the light level searched at (default: the plan's only one)
    start = [{ "optics.f_number" = 2.0, "optics.exposure_ms" = 10.0 }]  # designs tried first (optional)
    known = ["preset"]              # plan cameras whose design (their config's searched keys) and score the sampler
                                    # starts from, without training them again
    learned = ["learned"]           # plan cameras that learn searched keys: their learned design is tried first
    batch = 2                       # designs trained at once (fills a pool of GPUs)
    reduction = 3                   # successive halving: a design goes on to its next rung of cells only if its
                                    # score so far is in the top 1/reduction of the designs that reached that rung
    prune_margin = 0.0              # ... or within this much mIoU of that rung's best (only clear losers stop)
    sampler = "gp"                  # gp (Optuna's GPSampler, log expected improvement) | tpe
    seed = 0                        # the sampler's seed
    grid_points = { "optics.f_number" = 4, "optics.exposure_ms" = 4 }  # without a [[sweep]]: the grid it replaces

A design is a camera named ``<name>_<label><value>_...`` (`warpsense.study.keys.value_label`: "1p76" for 1.76),
with the search's preset and overrides and ``key=value`` per searched key; its cells are the plan's folds x the
first ``seeds`` seeds at ``light``. The name alone says the design (`design_values` reads it back), so a worker
process, a Slurm task or ``--cell`` resolves a design's cell from the plan and its name, without the search's state.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from dataclasses import dataclass

from warpsense.config import Config, flatten_keys
from warpsense.study.keys import value_label

SEARCH_KEYS = {"name": str, "preset": str, "set": list, "bounds": dict, "log": dict, "labels": dict, "digits": int,
               "budget": int, "seeds": int, "light": str, "start": list, "known": list, "learned": list, "batch": int,
               "reduction": int, "prune_margin": (int, float), "sampler": str, "seed": int, "grid_points": dict}
"""The keys of a ``[[search]]`` table and their types."""

SAMPLERS = ("gp", "tpe")
"""Optuna's samplers a search can take: GPSampler (the default) or TPESampler (multivariate)."""

DEFAULT_GRID_POINTS = 4
"""Points per searched key of the grid a search replaces, where the plan has no sweep and grid_points says none."""


class SearchError(ValueError):
    """A ``[[search]]`` table that cannot run; the message names the key."""


@dataclass(frozen=True)
class SearchSpec:
    """A checked ``[[search]]`` table (see the module's docstring); ``parameters`` in the table's order of
    ``bounds``, with their ``low``, ``high``, ``log`` flags and name ``labels``; ``start`` the start designs as
    tuples of values in that order."""

    name: str
    parameters: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    log: tuple[bool, ...]
    labels: tuple[str, ...]
    budget: int
    light: str
    preset: str = ""
    set: tuple[str, ...] = ()
    digits: int = 3
    seeds: int = 1
    start: tuple[tuple[float, ...], ...] = ()
    known: tuple[str, ...] = ()
    learned: tuple[str, ...] = ()
    batch: int = 1
    reduction: int = 3
    prune_margin: float = 0.0
    sampler: str = "gp"
    seed: int = 0
    grid_points: tuple[int, ...] = ()

    def rounded(self, values) -> tuple[float, ...]:
        """``values`` (one per parameter) clipped to the bounds and rounded to ``digits`` significant digits (the
        rounded value clipped again, so a bound stays inside)."""
        out = []
        for value, low, high in zip(values, self.low, self.high):
            value = min(max(float(value), low), high)
            value = float(f"{value:.{self.digits}g}")
            out.append(min(max(value, low), high))
        return tuple(out)

    def camera(self, values) -> str:
        """The design camera's name: ``<name>_<label><value>_...``."""
        return "_".join([self.name, *(f"{label}{value_label(float(v))}" for label, v in zip(self.labels, values))])

    def overrides(self, values) -> list[str]:
        """A design's overrides: the search's ``set``, then ``key=value`` per parameter."""
        return [*self.set, *(f"{key}={json.dumps(float(value))}" for key, value in zip(self.parameters, values))]

    def design_values(self, camera: str) -> tuple[float, ...] | None:
        """The values a design camera's name says (the inverse of `camera` for rounded values within the bounds);
        None where ``camera`` is not a design of this search."""
        prefix = self.name + "_"
        if not camera.startswith(prefix):
            return None
        parts = camera[len(prefix):].split("_")
        if len(parts) != len(self.labels):
            return None
        values = []
        for part, label in zip(parts, self.labels):
            if not part.startswith(label):
                return None
            text = part[len(label):].replace("m", "-").replace("p", ".")
            try:
                values.append(float(text))
            except ValueError:
                return None
        values = tuple(values)
        if self.rounded(values) != values or self.camera(values) != camera:
            return None
        return values

    def design_cost(self, folds: int) -> int:
        """Cells of one design: the plan's folds x ``seeds``."""
        return folds * self.seeds

    def rungs(self, folds: int) -> list[int]:
        """Successive halving's rungs, in cells of a design: its first cell, then reduction, reduction^2, ... cells
        while the next rung holds at least reduction times as many (a rung of 9 before 10 would decide nothing),
        then all of them (one rung, the whole design, with reduction < 2). 5 folds x 2 seeds: 1, 3, 10."""
        cost = self.design_cost(folds)
        if self.reduction < 2:
            return [cost]
        rungs, size = [], 1
        while size < cost and (size == 1 or size * self.reduction <= cost):
            rungs.append(size)
            size *= self.reduction
        return [*rungs, cost]

    def grid_values(self) -> list[list[float]]:
        """The grid the search replaces where the plan has no sweep: ``grid_points`` values per parameter, evenly
        spaced over its bounds (on a log scale where ``log``)."""
        values = []
        for low, high, log, points in zip(self.low, self.high, self.log, self.grid_points):
            if points == 1:
                values.append([low])
            elif log:
                values.append([math.exp(math.log(low) + i * (math.log(high) - math.log(low)) / (points - 1))
                               for i in range(points)])
            else:
                values.append([low + i * (high - low) / (points - 1) for i in range(points)])
        return [[float(f"{value:.4g}") for value in row] for row in values]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "SearchSpec":
        fields = {f.name: f for f in dataclasses.fields(cls)}
        values = {}
        for key, value in data.items():
            if key not in fields:
                continue
            if key == "start":
                value = tuple(tuple(point) for point in value)
            elif isinstance(value, list):
                value = tuple(value)
            values[key] = value
        return cls(**values)


def _float_key(key: str, where: str) -> None:
    """``key`` names a float field of the config ("section.field"), else a SearchError."""
    section, _, name = key.partition(".")
    sections = {f.name: f for f in dataclasses.fields(Config)}
    part = getattr(Config(), section, None) if section in sections else None
    fields = {f.name for f in dataclasses.fields(part)} if part is not None else set()
    if name not in fields:
        raise SearchError(f"{where}: {key!r} is not a config key (section.key, e.g. optics.f_number)")
    if isinstance(getattr(part, name), bool) or not isinstance(getattr(part, name), float):
        raise SearchError(f"{where}: {key!r} is not a continuous (float) config key; a search proposes numbers")


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _keyed(table: dict, key: str, where: str, parameters, check) -> dict:
    """``table[key]`` (config key -> value) flattened, its keys among ``parameters`` and each value passing
    ``check`` (a predicate, with the expectation in words as ``check.expected``)."""
    values = flatten_keys(table.get(key, {}))
    for name, value in values.items():
        if name not in parameters:
            raise SearchError(f"{where}.{key}.{name}: not a key of bounds; keys: {', '.join(parameters)}")
        if not check(value):
            raise SearchError(f"{where}.{key}.{name}: expected {check.expected}, got {value!r}")
    return values


def _expect(predicate, expected: str):
    predicate.expected = expected
    return predicate


def parse_search(table: dict, where: str, lights: list[str], cameras: list[str]) -> SearchSpec:
    """A checked ``[[search]]`` table (keys, types, bounds, labels, start designs, learned cameras, light).

    Args:
        table: the TOML table.
        where: "<plan file>: search[i]" for messages.
        lights: the plan's light names.
        cameras: the plan's camera names (those of [[camera]] and [[sweep]] tables).

    Raises:
        SearchError: one line naming the key.
    """
    for key, value in table.items():
        if key not in SEARCH_KEYS:
            raise SearchError(f"{where}.{key}: unknown key; valid keys: {', '.join(SEARCH_KEYS)}")
        expected = SEARCH_KEYS[key]
        if isinstance(value, bool) or not isinstance(value, expected):
            kinds = " or ".join(t.__name__ for t in (expected if isinstance(expected, tuple) else (expected,)))
            raise SearchError(f"{where}.{key}: expected {kinds}, got {type(value).__name__} {value!r}")
    for key in ("name", "bounds", "budget"):
        if key not in table:
            raise SearchError(f"{where}.{key}: missing")
    bounds = flatten_keys(table["bounds"])
    if not bounds:
        raise SearchError(f"{where}.bounds: give at least one config key and its [low, high]")
    for key, pair in bounds.items():
        _float_key(key, f"{where}.bounds.{key}")
        if not (isinstance(pair, list) and len(pair) == 2 and all(_number(v) for v in pair) and pair[0] < pair[1]):
            raise SearchError(f"{where}.bounds.{key}: expected [low, high] with low < high, got {pair!r}")
    parameters = list(bounds)
    log = _keyed(table, "log", where, parameters, _expect(lambda v: isinstance(v, bool), "true or false"))
    for key, flag in log.items():
        if flag and bounds[key][0] <= 0:
            raise SearchError(f"{where}.log.{key}: a log scale needs low > 0, got {bounds[key][0]}")
    labels = _keyed(table, "labels", where, parameters, _expect(
        lambda v: isinstance(v, str) and v and v.isascii() and v.replace("-", "").isalpha() and "m" not in v
        and "p" not in v, "a short name of letters (no 'p' or 'm': they spell a value's point and minus)"))
    names = tuple(labels.get(key, key.rsplit(".", 1)[-1].replace("_", "")) for key in parameters)
    for key, name in zip(parameters, names):
        if key not in labels and ("p" in name or "m" in name or not name.isalpha()):
            raise SearchError(f"{where}.labels.{key}: give a label (letters without 'p' or 'm', which spell a value's "
                              f"point and minus); the key's own name {name!r} cannot be read back from a camera name")
    if len(set(names)) != len(names):
        raise SearchError(f"{where}.labels: the keys need distinct labels, got {', '.join(names)}")
    name = table["name"]
    if not name or "/" in name or "." in name or name != name.strip() or " " in name:
        raise SearchError(f"{where}.name: {name!r} must be a plain name (no '/', '.' or spaces)")
    for key in ("digits", "budget", "seeds", "batch"):
        if key in table and table[key] < 1:
            raise SearchError(f"{where}.{key}: expected an integer >= 1, got {table[key]}")
    if table.get("digits", 3) > 6:
        raise SearchError(f"{where}.digits: at most 6 significant digits (a camera name), got {table['digits']}")
    if table.get("reduction", 3) < 0:
        raise SearchError(f"{where}.reduction: expected 0 (no pruning) or an integer >= 2, got {table['reduction']}")
    if table.get("reduction", 3) == 1:
        raise SearchError(f"{where}.reduction: 1 keeps every design (no pruning): write 0, or 2 and more")
    if not 0 <= table.get("prune_margin", 0.0) < 1:
        raise SearchError(f"{where}.prune_margin: expected a difference of mIoU in [0, 1), got {table['prune_margin']}")
    if table.get("sampler", "gp") not in SAMPLERS:
        raise SearchError(f"{where}.sampler: {table['sampler']!r} is not a sampler; samplers: {', '.join(SAMPLERS)}")
    light = table.get("light")
    if light is None:
        if len(lights) != 1:
            raise SearchError(f"{where}.light: the plan has {len(lights)} light levels ({', '.join(lights)}): name "
                              "the one searched at")
        light = lights[0]
    elif light not in lights:
        raise SearchError(f"{where}.light: {light!r} is not a light of the plan; lights: {', '.join(lights)}")
    start = []
    for i, point in enumerate(table.get("start", [])):
        if not isinstance(point, dict):
            raise SearchError(f"{where}.start[{i}]: expected a table of config key -> value")
        point = flatten_keys(point)
        for key, value in point.items():
            if key not in bounds:
                raise SearchError(f"{where}.start[{i}].{key}: not a key of bounds; keys: {', '.join(parameters)}")
            if not (_number(value) and bounds[key][0] <= value <= bounds[key][1]):
                raise SearchError(f"{where}.start[{i}].{key}: expected a number within the bounds {bounds[key]}, got "
                                  f"{value!r}")
        missing = [key for key in parameters if key not in point]
        if missing:
            raise SearchError(f"{where}.start[{i}]: give a value of every searched key; missing {', '.join(missing)}")
        start.append(tuple(float(point[key]) for key in parameters))
    learned, known = table.get("learned", []), table.get("known", [])
    for key, listed in (("learned", learned), ("known", known)):
        for camera in listed:
            if camera not in cameras:
                raise SearchError(f"{where}.{key}: {camera!r} is not a camera of the plan; cameras: "
                                  f"{', '.join(cameras)}")
    grid = _keyed(table, "grid_points", where, parameters, _expect(
        lambda v: isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 100, "an integer in 1..100"))
    spec = SearchSpec(
        name=name, parameters=tuple(parameters), low=tuple(float(bounds[k][0]) for k in parameters),
        high=tuple(float(bounds[k][1]) for k in parameters), log=tuple(bool(log.get(k, False)) for k in parameters),
        labels=names, budget=table["budget"], light=light, preset=table.get("preset", ""),
        set=tuple(table.get("set", [])), digits=table.get("digits", 3), seeds=table.get("seeds", 1),
        start=tuple(start), known=tuple(known), learned=tuple(learned), batch=table.get("batch", 1),
        reduction=table.get("reduction", 3),
        prune_margin=float(table.get("prune_margin", 0.0)), sampler=table.get("sampler", "gp"),
        seed=table.get("seed", 0), grid_points=tuple(grid.get(k, DEFAULT_GRID_POINTS) for k in parameters))
    if not all(isinstance(text, str) for text in spec.set):
        raise SearchError(f"{where}.set: expected a list of \"section.key=value\" strings")
    for corner in itertools.product(*zip(spec.low, spec.high)):  # a bound's name reads back as the bound
        if spec.design_values(spec.camera(spec.rounded(corner))) is None:
            raise SearchError(f"{where}.labels: a design's name ({spec.camera(spec.rounded(corner))}) does not read "
                              "back as its values; choose other labels")
    return spec


def corner_designs(spec: SearchSpec) -> list[tuple[float, ...]]:
    """The designs at the corners of the bounds (every config the search can propose lies between them)."""
    return [spec.rounded(corner) for corner in itertools.product(*zip(spec.low, spec.high))]
