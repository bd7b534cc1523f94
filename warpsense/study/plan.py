"""Study plans: which cameras, at which light levels, over which seeds, against which reference camera.

A plan is a TOML file (see `configs/studies/`)::

    [study]
    name = "camvid_cameras"
    base = "camvid"                 # preset or TOML file every cell starts from ("" = the defaults)
    set = ["train.epochs=100"]      # overrides for every cell
    seeds = [0, 1, 2]
    reference = "fixed_isp"         # the camera the others are compared with, seed by seed
    folds = "blocks"                # "blocks": a cell per block fold (buffered blocked cross-validation: block j of
                                    # every sequence of train + val judged, the rest less a buffer trained on);
                                    # "sequence": a cell per held-out sequence (train on the others' frames of train +
                                    # val, judge on its frames); "none": train on train, judge on val
    blocks = 5                      # with folds = "blocks": blocks per sequence, one fold each
    block_buffer = 30               # with folds = "blocks": frame numbers around a held-out block left out of training
    sequences = []                  # with folds = "sequence": the sequences held out, one fold each (default: all)
    sequential = {min_seeds = 3, max_seeds = 8, tolerance = 0.01}  # optional: min_seeds seeds for every cell, then
                                    # one more seed at a time for each comparison whose interval holds 0 and is wider
                                    # than +-tolerance, up to max_seeds (`warpsense.study.sequential`); seeds lists
                                    # the first ones, the rest follow the last

    [[camera]]
    name = "fixed_isp"
    preset = "camvid_fixed_isp"     # applied over the base ("" = none)
    set = []                        # overrides of this camera
    seed_offset = 0                 # the camera's runs train with run.seed = the cell's seed + this: a twin of another
                                    # camera (same preset, another name, an offset) is an independent replicate of it,
                                    # an A/A check of the verdicts (with 0 it would repeat the other's runs exactly)

    [[light]]
    name = "night"
    full_well_electrons = 66.667    # electrons at the white level
    read_electrons = 0.13333        # read noise, electrons rms
    bits = 10                       # ADC bit depth
    cameras = []                    # the cameras studied at this level (default: all)

    [[sweep]]                       # a grid of cameras: the Cartesian product of the values, one camera each
    name = "grid"                   # the cameras' name prefix (and the sweep's name on the report's map)
    preset = ""                     # as a camera's (optional)
    set = []                        # overrides of every point (optional)
    grid = { "optics.f_number" = [1.4, 2.0], "optics.exposure_ms" = [3.0, 30.0] }  # config key -> values
    labels = { "optics.f_number" = "f", "optics.exposure_ms" = "t" }  # name labels (default: the key's last part)

    [[light]]                       # or, with the photon budget (photons.enabled): a scene light level
    name = "day"
    scene = "day"                   # photons.light: night | dusk | day
    analog_gain = 2.0               # photons.analog_gain (optional)
    set = ["optics.exposure_ms=2.5"]  # the operating point at this level (optional)

A ``[[search]]`` table (`warpsense.study.search_space`) adds the designs a Bayesian search proposes within bounds
of config keys: each a camera named after its values, trained by `warpsense.study.search`.

Every cell (camera x light x seed, and x fold with ``folds = "blocks"`` or ``"sequence"``) is one ordinary training
run; its config is the base, the camera's preset, the study's and the camera's overrides, the light's sensor keys, the
fold's ``data.holdout_block`` (with ``data.holdout_blocks`` and ``data.block_buffer``) or ``data.holdout_sequence``,
the seed (plus the camera's ``seed_offset``), then the command line's ``--set`` (whose ``study.KEY=VALUE`` entries
change the plan's [study] table instead, e.g. ``--set study.folds=none``). In any of these overrides ``{fold}`` and
``{seed}`` stand for the cell's fold ("block2", or the held-out sequence) and seed (`fill_placeholders`), for inputs
made per fold. A sweep's point is
a camera like the others (crossed with lights, folds and seeds; the reference may be one), named
``<name>_<label><value>_...`` in the grid's key order (``grid_f1p4_t30``): camera names hold no '.', which
separates a run directory's parts, so a value's decimal point is written ``p`` and a minus sign ``m``. Unknown keys, wrong types, duplicate or unknown names,
folds that hold no frame, a dataset without sequence names and configs that do not resolve are one-line `PlanError`s
naming the plan file and key, found before anything is written.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import itertools
import json
from dataclasses import dataclass
from pathlib import Path

from warpsense.choices import LIGHT_LEVELS
from warpsense.config import Config, ConfigError, flatten_keys, load_config, parse_override, read_toml
from warpsense.data import DatasetError, build_dataset, sequence_names
from warpsense.resources import CONFIG_DIR
from warpsense.study.conflicts import check_conflicts
from warpsense.study.keys import LEARNED_KEYS, value_label
from warpsense.study.search_space import SearchError, SearchSpec, corner_designs, parse_search
from warpsense.study.sequential import SequentialRule, check_rule


class PlanError(ValueError):
    """A study plan that cannot run; the message names the plan file and key."""


@dataclass(frozen=True)
class CameraSpec:
    name: str
    preset: str = ""
    set: tuple[str, ...] = ()
    seed_offset: int = 0


@dataclass(frozen=True)
class SweepSpec:
    """A ``[[sweep]]`` table as the plan resolved it: the swept config keys (``parameters``, in the grid's order),
    their name labels and values, and per grid point its camera's name and its value of each key (``points``)."""

    name: str
    preset: str = ""
    set: tuple[str, ...] = ()
    parameters: tuple[str, ...] = ()
    labels: tuple[str, ...] = ()
    values: tuple[tuple, ...] = ()
    points: tuple[tuple[str, tuple], ...] = ()  # (camera, (value per parameter))

    @classmethod
    def from_dict(cls, data: dict) -> "SweepSpec":
        return cls(data["name"], data.get("preset", ""), tuple(data.get("set", ())), tuple(data["parameters"]),
                   tuple(data["labels"]), tuple(tuple(v) for v in data["values"]),
                   tuple((camera, tuple(values)) for camera, values in data["points"]))


@dataclass(frozen=True)
class LightSpec:
    """A light level stated physically: for the noise stage, electrons at the white level (full well) and read noise
    in electrons; for the photon budget, a scene light level (``scene``, `warpsense.choices.LIGHT_LEVELS`) with the
    analog gain and, where given, the full well and read noise; ADC bits; and the operating point's other overrides
    (``set``)."""

    name: str
    full_well_electrons: float | None = None
    read_electrons: float | None = None
    bits: int = 10
    cameras: tuple[str, ...] = ()  # the cameras studied at this level (empty: all)
    scene: str = ""
    analog_gain: float | None = None
    set: tuple[str, ...] = ()

    def overrides(self) -> list[str]:
        if self.scene:
            keys = [f"photons.light={self.scene!r}".replace("'", '"')]
            for key in ("analog_gain", "full_well_electrons", "read_electrons"):
                if getattr(self, key) is not None:
                    keys.append(f"photons.{key}={getattr(self, key)!r}")
        else:
            keys = [f"noise.full_well_electrons={self.full_well_electrons!r}",
                    f"noise.read_electrons={self.read_electrons!r}"]
        return [*keys, f"quantize.bits={self.bits}", *self.set]


FOLDS = ("none", "blocks", "sequence")
"""A study's protocol: "none" (train on the train split, judge on val), "blocks" (one fold per block of every
sequence of the labelled splits, buffered: `warpsense.data.block_fold`) or "sequence" (one fold per held-out
sequence of the labelled splits)."""

BLOCK_FOLD = "block"
"""Block folds are named BLOCK_FOLD + their number: "block1" ... "block5"."""


@dataclass(frozen=True)
class Cell:
    """One training run of a study; ``fold`` is the fold's name ("block2", the held-out sequence; "" without
    folds)."""

    camera: str
    light: str
    seed: int
    fold: str = ""

    @property
    def id(self) -> str:
        """"camera/light/seed", or "camera/light/fold/seed" with folds, as `--cell` takes it."""
        return "/".join([self.camera, self.light, *([self.fold] if self.fold else []), str(self.seed)])

    @property
    def run_name(self) -> str:
        """The run directory's name under <out>/runs."""
        return ".".join([self.camera, self.light, *([self.fold] if self.fold else []), f"seed{self.seed}"])


@dataclass(frozen=True)
class Plan:
    source: str
    name: str
    base: str
    set: tuple[str, ...]
    seeds: tuple[int, ...]
    reference: str
    cameras: tuple[CameraSpec, ...]
    lights: tuple[LightSpec, ...]
    overrides: tuple[str, ...] = ()  # from the command line, applied last
    folds: str = "none"  # FOLDS
    sequences: tuple[str, ...] = ()  # the held-out sequences, one fold each (folds = "sequence")
    sweeps: tuple[SweepSpec, ...] = ()  # where the cameras of [[sweep]] tables came from (they are in ``cameras``)
    blocks: int = 5  # folds = "blocks": blocks per sequence, one fold each
    block_buffer: int = 30  # folds = "blocks": frame numbers around a held-out block left out of training
    sequential: SequentialRule | None = None  # study.sequential: seeds added while comparisons are unsettled
    search: SearchSpec | None = None  # a [[search]] table: designs proposed by a Bayesian search
    designs: tuple[str, ...] = ()  # the search's designs started so far (their cells join `cells`; not recorded)

    def with_designs(self, cameras) -> "Plan":
        """This plan with the search's design ``cameras`` among its cells (`cells`, `cell`), as a round of the search
        trains them; its record (`to_dict`) is the plan's own."""
        return dataclasses.replace(self, designs=tuple(dict.fromkeys([*self.designs, *cameras])))

    def camera_spec(self, name: str) -> CameraSpec | None:
        """The camera ``name``: one of the plan's cameras, or a design of its search (`SearchSpec.design_values`:
        the name says the design); None otherwise."""
        for camera in self.cameras:
            if camera.name == name:
                return camera
        values = self.search.design_values(name) if self.search is not None else None
        if values is None:
            return None
        return CameraSpec(name, self.search.preset, tuple(self.search.overrides(values)))

    def design_cells(self, camera: str) -> list[Cell]:
        """A search design's cells in the order its rungs take them: seed by seed (the first ``search.seeds`` of
        the plan's seeds), fold by fold, at the search's light."""
        return [Cell(camera, self.search.light, seed, fold) for seed in self.seeds[:self.search.seeds]
                for fold in self.fold_names()]

    def fold_names(self) -> tuple[str, ...]:
        """The folds' names, in order ("block1".., the held-out sequences; one "" without folds)."""
        if self.folds == "blocks":
            return tuple(f"{BLOCK_FOLD}{j}" for j in range(1, self.blocks + 1))
        return self.sequences if self.folds == "sequence" else ("",)

    def fold_overrides(self, fold: str) -> list[str]:
        """The data keys that make a run fold ``fold`` of this plan (none for "")."""
        if not fold:
            return []
        if self.folds == "blocks":
            return [f"data.holdout_block={int(fold.removeprefix(BLOCK_FOLD))}", f"data.holdout_blocks={self.blocks}",
                    f"data.block_buffer={self.block_buffer}"]
        return [f"data.holdout_sequence={json.dumps(fold)}"]

    def cells(self) -> list[Cell]:
        """Every cell, light by light, seed by seed, fold by fold, camera by camera (so a partial study run in this
        order has whole comparisons: every fold of seed 0 before seed 1). The local pool and the Slurm executor hand
        them out longest first instead (`warpsense.study.runner.cell_work`), the order that finishes a study
        soonest; cells of equal work (the cameras of one fold and seed, as a rule) keep this order."""
        folds = self.fold_names()
        return [Cell(camera.name, light.name, seed, fold) for light in self.lights for seed in self.seeds
                for fold in folds for camera in self.cameras if not light.cameras or camera.name in light.cameras] \
            + [cell for camera in self.designs for cell in self.design_cells(camera)]

    def cell(self, cell_id: str) -> Cell:
        for cell in self.cells():
            if cell.id == cell_id:
                return cell
        camera = cell_id.split("/", 1)[0]
        if self.search is not None and camera not in {c.name for c in self.cameras} and self.camera_spec(camera):
            for cell in self.design_cells(camera):  # a design of the search: its name says its config
                if cell.id == cell_id:
                    return cell
        form = "camera/light/fold/seed" if self.folds != "none" else "camera/light/seed"
        raise PlanError(f"{self.source}: no cell {cell_id!r}; cells are {form}, e.g. {self.cells()[0].id}")

    def select(self, patterns: list[str] | tuple[str, ...]) -> list[Cell]:
        """The cells whose id (`Cell.id`) matches any of the shell ``patterns`` (`fnmatch`: "fixed_isp/*",
        "*/night/block1/*"), in plan order; every cell without patterns. A pattern that matches no cell is a
        PlanError naming it."""
        cells = self.cells()
        if not patterns:
            return cells
        for pattern in patterns:
            if not any(fnmatch.fnmatchcase(cell.id, pattern) for cell in cells):
                form = "camera/light/fold/seed" if self.folds != "none" else "camera/light/seed"
                raise PlanError(f"{self.source}: --cells {pattern!r} matches no cell; cells are {form}, e.g. "
                                f"{cells[0].id}")
        return [cell for cell in cells if any(fnmatch.fnmatchcase(cell.id, pattern) for pattern in patterns)]

    def config(self, cell: Cell, output_dir: str | Path) -> Config:
        """The resolved config of ``cell``, its run directory <output_dir>/<cell.run_name>."""
        camera = self.camera_spec(cell.camera)
        light = next(light for light in self.lights if light.name == cell.light)
        files = [file for file in (self.base, camera.preset) if file]
        overrides = [*self.set, *camera.set, *light.overrides(), *self.fold_overrides(cell.fold),
                     f"run.seed={cell.seed + camera.seed_offset}",
                     f"run.name={cell.run_name}", f"run.output_dir={output_dir}", *cell_overrides(self.overrides)]
        return load_config(files, [fill_placeholders(text, cell) for text in overrides])

    def to_dict(self) -> dict:
        """The plan as JSON-ready data; ``sweeps`` only where it has some, the block keys only with block folds and a
        camera's ``seed_offset`` only where it is set (a study directory recorded before plans had them holds the
        same plan)."""
        data = dataclasses.asdict(self)
        if not self.sweeps:
            del data["sweeps"]
        del data["designs"]  # the search's state, kept in the study directory (warpsense.study.search)
        for key in ("sequential", "search"):  # absent where unused: a directory recorded before them matches
            if data[key] is None:
                del data[key]
        if self.sequential is not None:
            data["sequential"] = self.sequential.to_dict()
        if self.folds != "blocks":
            del data["blocks"], data["block_buffer"]
        for camera in data["cameras"]:
            if not camera["seed_offset"]:
                del camera["seed_offset"]
        return data

    @classmethod
    def from_dict(cls, data: dict) -> "Plan":
        """The plan `to_dict` wrote (a study directory's plan.json)."""
        return cls(source=data.get("source", ""), name=data["name"], base=data["base"], set=tuple(data["set"]),
                   seeds=tuple(data["seeds"]), reference=data["reference"], folds=data.get("folds", "none"),
                   sequences=tuple(data.get("sequences", ())), blocks=data.get("blocks", 5),
                   block_buffer=data.get("block_buffer", 30),
                   cameras=tuple(CameraSpec(c["name"], c["preset"], tuple(c["set"]), c.get("seed_offset", 0))
                                 for c in data["cameras"]),
                   lights=tuple(LightSpec(x["name"], x.get("full_well_electrons"), x.get("read_electrons"),
                                          x["bits"], tuple(x["cameras"]), x.get("scene", ""),
                                          x.get("analog_gain"), tuple(x.get("set", ()))) for x in data["lights"]),
                   overrides=tuple(data.get("overrides", ())),
                   sweeps=tuple(SweepSpec.from_dict(sweep) for sweep in data.get("sweeps", ())),
                   sequential=SequentialRule.from_dict(data["sequential"]) if data.get("sequential") else None,
                   search=SearchSpec.from_dict(data["search"]) if data.get("search") else None)


STUDY_KEYS = {"name": str, "base": str, "set": list, "seeds": list, "reference": str, "folds": str, "sequences": list,
              "blocks": int, "block_buffer": int, "sequential": dict}


CAMERA_KEYS = {"name": str, "preset": str, "set": list, "seed_offset": int}
SWEEP_KEYS = {"name": str, "preset": str, "set": list, "grid": dict, "labels": dict}
LIGHT_KEYS = {"name": str, "full_well_electrons": (int, float), "read_electrons": (int, float), "bits": int,
              "cameras": list, "scene": str, "analog_gain": (int, float), "set": list}


def _is_study_override(text: str) -> bool:
    """Whether a ``--set`` entry changes the plan (``study.KEY`` its [study] table, ``search.KEY`` its [[search]])
    rather than every cell's config."""
    return text.split("=", 1)[0].strip().startswith(("study.", "search."))


def fill_placeholders(text: str, cell: "Cell") -> str:
    """``text`` (an override) with ``{fold}`` and ``{seed}`` replaced by ``cell``'s held-out sequence and seed: a
    per-fold input, such as a distillation teacher trained without the held-out drive
    (``loss.teacher="teachers/runs/rgb.night.{fold}.seed0/..."``)."""
    return text.replace("{fold}", cell.fold).replace("{seed}", str(cell.seed))


def cell_overrides(overrides) -> list[str]:
    """The command line's ``--set`` entries for the cells' configs (``study.KEY=VALUE`` ones change the plan)."""
    return [text for text in overrides if not _is_study_override(text)]


def _study_overrides(study: dict, overrides, source: str, table: str = "study") -> dict:
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


def study_names() -> list[str]:
    """The plans shipped in configs/studies/."""
    return sorted(p.name[:-5] for p in (CONFIG_DIR / "studies").iterdir() if p.name.endswith(".toml"))


def _table(data: dict, keys: dict, where: str, required: tuple[str, ...]) -> dict:
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


def _strings(values: list, where: str) -> tuple[str, ...]:
    if not all(isinstance(value, str) for value in values):
        raise PlanError(f"{where}: expected a list of \"section.key=value\" strings")
    return tuple(values)


def _float(value) -> float | None:
    return None if value is None else float(value)


def _plain(text: str) -> bool:
    """Whether ``text`` can be part of a cell id and a run directory's name: no '/', no '.', no spaces at the ends."""
    return "/" not in text and "." not in text and text == text.strip()


def _names(items: list, where: str, other: str = "") -> None:
    seen = set()
    for item in items:
        name = item["name"]
        if not name or not _plain(name):
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


def _sweep(table: dict, where: str) -> SweepSpec:
    """A checked ``[[sweep]]`` table with its points (the grid's Cartesian product, first key slowest)."""
    table = _table(table, SWEEP_KEYS, where, ("name", "grid"))
    grid, labels = flatten_keys(table["grid"]), flatten_keys(table.get("labels", {}))
    if not grid:
        raise PlanError(f"{where}.grid: give at least one config key and its values")
    for key, values in grid.items():
        _config_key(key, f"{where}.grid.{key}")
        if not isinstance(values, list) or not values:
            raise PlanError(f"{where}.grid.{key}: expected a non-empty list of values, got {values!r}")
        if not all(isinstance(v, (str, int, float, bool)) for v in values) or len(set(map(repr, values))) != len(values):
            raise PlanError(f"{where}.grid.{key}: expected distinct numbers, strings or booleans, got {values!r}")
    for key, label in labels.items():
        if key not in grid:
            raise PlanError(f"{where}.labels.{key}: not a key of the grid; keys: {', '.join(grid)}")
        if not isinstance(label, str) or not _plain(label):
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
    return SweepSpec(table["name"], table.get("preset", ""), _strings(table.get("set", []), f"{where}.set"),
                     tuple(grid), names, tuple(tuple(v) for v in grid.values()), tuple(points))


def _point_overrides(sweep: SweepSpec, values: tuple) -> list[str]:
    """A grid point's overrides: ``key=value`` per swept key (after the sweep's ``set``)."""
    return [f"{key}={json.dumps(value)}" for key, value in zip(sweep.parameters, values)]


def _locate(name_or_path: str | Path) -> Path:
    path = Path(name_or_path)
    if not path.suffix and str(name_or_path) in study_names():
        return Path(str(CONFIG_DIR / "studies" / f"{name_or_path}.toml"))
    return path


def load_plan(name_or_path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> Plan:
    """Read, check and resolve a plan (a shipped name from configs/studies or a TOML path); ``overrides`` are
    ``section.key=value`` strings for every cell. Every cell's config is resolved here, so a bad key anywhere is
    found before any run starts."""
    path = _locate(name_or_path)
    source = str(path)
    try:
        data = read_toml(path, source)
    except ConfigError as error:
        hint = "" if path.is_file() else f"; shipped plans: {', '.join(study_names())}"
        raise PlanError(f"{error}{hint}") from None
    for key in data:
        if key not in ("study", "camera", "light", "sweep", "search"):
            raise PlanError(f"{source}: unknown table [{key}]; valid tables: [study], [[camera]], [[sweep]], "
                            "[[search]], [[light]]")
    study = data.get("study")
    if not isinstance(study, dict):
        raise PlanError(f"{source}: [study] table missing")
    study = _table(_study_overrides(study, overrides, source), STUDY_KEYS, f"{source}: study", ("seeds", "reference"))
    if study.get("folds", "none") not in FOLDS:
        raise PlanError(f"{source}: study.folds: {study['folds']!r} is not a protocol; valid: {', '.join(FOLDS)}")
    if study.get("sequences") and study.get("folds", "none") != "sequence":
        raise PlanError(f"{source}: study.sequences: held-out sequences need folds = \"sequence\"")
    for key in ("blocks", "block_buffer"):
        if key in study and study.get("folds", "none") != "blocks":
            raise PlanError(f"{source}: study.{key}: block folds' {key} needs folds = \"blocks\"")
    if not study.get("blocks", 5) >= 2 or not study.get("block_buffer", 0) >= 0:
        raise PlanError(f"{source}: study.{'blocks' if study.get('blocks', 5) < 2 else 'block_buffer'}: blocks must "
                        f"be >= 2 (folds), block_buffer >= 0 (frame numbers), got {study.get('blocks', 5)} and "
                        f"{study.get('block_buffer', 30)}")
    cameras, lights, sweep_tables = data.get("camera", []), data.get("light"), data.get("sweep", [])
    if not isinstance(sweep_tables, list) or not all(isinstance(table, dict) for table in sweep_tables):
        raise PlanError(f"{source}: sweep: expected [[sweep]] tables")
    if not isinstance(cameras, list) or not all(isinstance(c, dict) for c in cameras) or not (cameras or sweep_tables):
        raise PlanError(f"{source}: camera: at least one [[camera]] or [[sweep]] table is needed")
    if not isinstance(lights, list) or not lights:
        raise PlanError(f"{source}: light: at least one [[light]] table is needed")
    cameras = [_table(c, CAMERA_KEYS, f"{source}: camera[{i}]", ("name",)) for i, c in enumerate(cameras)]
    lights = [_table(x, LIGHT_KEYS, f"{source}: light[{i}]", ("name",)) for i, x in enumerate(lights)]
    _names(cameras, f"{source}: camera")
    sweeps = [_sweep(table, f"{source}: sweep[{i}]") for i, table in enumerate(sweep_tables)]
    _names([{"name": sweep.name} for sweep in sweeps], f"{source}: sweep")  # before its points, named after it
    _names([*cameras, *({"name": camera} for sweep in sweeps for camera, _ in sweep.points)], f"{source}: camera",
           "a [[camera]] or another sweep's point")
    cameras += [{"name": camera, "preset": sweep.preset, "set": [*sweep.set, *_point_overrides(sweep, values)]}
                for sweep in sweeps for camera, values in sweep.points]
    _names(lights, f"{source}: light")
    seeds = study["seeds"]
    if not seeds or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in seeds) \
            or len(set(seeds)) != len(seeds):
        raise PlanError(f"{source}: study.seeds: expected distinct integers >= 0, got {seeds!r}")
    rule = _sequential_rule(study, source, 2)  # the rule's own keys here; its first look's pairs once folds are known
    if rule is not None:
        seeds = _sequential_seeds(seeds, rule, source)
    search = _search(data.get("search", []), source, [x["name"] for x in lights], [c["name"] for c in cameras],
                     overrides)
    if search is None and any(text.strip().startswith("search.") for text in overrides):
        raise PlanError(f"{source}: --set search.KEY: the plan has no [[search]] table")
    if search is not None and rule is not None:
        raise PlanError(f"{source}: study.sequential: a plan with a [[search]] judges its designs at search.seeds; "
                        "sequential verdicts add seeds to fixed comparisons: give one of them per plan")
    if search is not None and search.seeds > len(seeds):
        raise PlanError(f"{source}: search[0].seeds: {search.seeds} seeds per design, the study has {len(seeds)} "
                        "(study.seeds)")
    if study["reference"] not in [c["name"] for c in cameras]:
        raise PlanError(f"{source}: study.reference: {study['reference']!r} is not a camera of the plan; cameras: "
                        f"{', '.join(c['name'] for c in cameras)}")
    camera_names = [c["name"] for c in cameras]
    for i, light in enumerate(lights):
        if light.get("scene"):
            if light["scene"] not in LIGHT_LEVELS:
                raise PlanError(f"{source}: light[{i}].scene: {light['scene']!r} is not a light level; levels: "
                                f"{', '.join(LIGHT_LEVELS)}")
        elif "full_well_electrons" not in light or "read_electrons" not in light:
            raise PlanError(f"{source}: light[{i}]: give full_well_electrons and read_electrons (the noise stage) or "
                            "scene (the photon budget)")
        elif "analog_gain" in light:
            raise PlanError(f"{source}: light[{i}].analog_gain: only with scene (the photon budget)")
        if not light.get("full_well_electrons", 1) > 0 or not light.get("read_electrons", 0) >= 0:
            raise PlanError(f"{source}: light[{i}]: full_well_electrons must be > 0 and read_electrons >= 0")
        for name in light.get("cameras", []):
            if name not in camera_names:
                raise PlanError(f"{source}: light[{i}].cameras: {name!r} is not a camera of the plan; cameras: "
                                f"{', '.join(camera_names)}")
        if light.get("cameras") and study["reference"] not in light["cameras"]:
            raise PlanError(f"{source}: light[{i}].cameras: must include the reference camera {study['reference']!r}")
    from warpsense.system import check_config  # the stages' own checks (imports the camera)

    plan = Plan(
        source=source, name=study.get("name", path.stem), base=study.get("base", ""),
        set=_strings(study.get("set", []), f"{source}: study.set"), seeds=tuple(seeds),
        reference=study["reference"],
        cameras=tuple(CameraSpec(c["name"], c.get("preset", ""), _strings(c.get("set", []), f"{source}: camera "
                                                                           f"{c['name']}.set"),
                                 _seed_offset(c, source)) for c in cameras),
        lights=tuple(LightSpec(x["name"], _float(x.get("full_well_electrons")), _float(x.get("read_electrons")),
                               x.get("bits", 10), tuple(x.get("cameras", [])), x.get("scene", ""),
                               _float(x.get("analog_gain")),
                               _strings(x.get("set", []), f"{source}: light {x['name']}.set")) for x in lights),
        overrides=tuple(overrides), folds=study.get("folds", "none"), sweeps=tuple(sweeps),
        blocks=study.get("blocks", 5), block_buffer=study.get("block_buffer", 30), sequential=rule, search=search)
    if plan.folds == "sequence":
        plan = dataclasses.replace(plan, sequences=_fold_sequences(plan, study.get("sequences", [])))
    elif plan.folds == "blocks":
        fold_sizes(plan)  # every fold judges and trains on frames, else a PlanError naming it
    elif any("{fold}" in text for text in _all_overrides(plan)):
        raise PlanError(f"{source}: {{fold}} in a set stands for a cell's fold: it needs study.folds = \"blocks\" "
                        f"or \"sequence\"")
    if rule is not None:
        _sequential_rule(study, source, len(plan.fold_names()))
    if search is not None:
        _check_designs(plan)
    checked_data = set()
    for camera in plan.cameras:  # every cell's config resolves (seeds only change run.seed, folds the held-out name)
        for light in plan.lights:
            if light.cameras and camera.name not in light.cameras:
                continue
            where = f"{source}: camera {camera.name!r} at light {light.name!r}"
            try:
                config = plan.config(Cell(camera.name, light.name, plan.seeds[0], plan.fold_names()[0]), "runs")
                check_config(config, "config")
            except ConfigError as error:
                raise PlanError(f"{where}: {error}") from None
            if bool(light.scene) != config.photons.enabled:  # else the light's keys would change nothing
                raise PlanError(f"{where}: " + (
                    "the light states a scene level (scene), which needs the photon budget (photons.enabled)"
                    if light.scene else "the camera has a photon budget (photons.enabled): state the light as a "
                    "scene level (scene), not as noise-stage electrons"))
            data = (config.data.dataset, config.data.root, config.data.train_split, config.data.val_split)
            if data not in checked_data:
                checked_data.add(data)
                try:  # the split lists exist (reads file lists only)
                    for split, train in ((config.data.train_split, True), (config.data.val_split, False)):
                        build_dataset(config.data, split, train=train, seed=0)
                except DatasetError as error:
                    raise PlanError(f"{where}: data: {error}") from None
    check_conflicts(plan, PlanError)  # two tables setting one key differently: the plan would not say what runs
    return plan


def _sequential_rule(study: dict, source: str, pairs_per_seed: int) -> SequentialRule | None:
    """The plan's ``study.sequential`` rule checked (None without one), its first look holding ``pairs_per_seed`` x
    min_seeds pairs; a PlanError naming the key otherwise."""
    if "sequential" not in study:
        return None
    try:
        return check_rule(study["sequential"], f"{source}: study.sequential", pairs_per_seed)
    except ValueError as error:
        raise PlanError(str(error)) from None


def _sequential_seeds(seeds: list, rule: SequentialRule, source: str) -> list:
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


def _search(tables, source: str, lights: list[str], cameras: list[str], overrides) -> SearchSpec | None:
    """The plan's ``[[search]]`` (at most one), with the command line's ``search.KEY=VALUE`` entries, checked; a
    PlanError naming the key otherwise."""
    if not isinstance(tables, list) or not all(isinstance(table, dict) for table in tables):
        raise PlanError(f"{source}: search: expected a [[search]] table")
    if len(tables) > 1:
        raise PlanError(f"{source}: search: one [[search]] table per plan, got {len(tables)}")
    if not tables:
        return None
    try:
        return parse_search(_study_overrides(tables[0], overrides, source, "search"), f"{source}: search[0]", lights,
                            cameras)
    except SearchError as error:
        raise PlanError(str(error)) from None


def _check_designs(plan: Plan) -> None:
    """Every design the search can propose resolves (its configs at the bounds' corners pass the config's and the
    stages' checks), says the searched values in its config (nothing later in a cell's overrides, a light's keys
    or --set, changes them), no plan camera is named as a design, a known camera's design lies within the bounds
    and a learned camera learns a searched key; else a PlanError naming the search."""
    from warpsense.system import check_config

    search, where = plan.search, f"{plan.source}: search[0]"
    first = {camera: Cell(camera, search.light, plan.seeds[0], plan.fold_names()[0]) for camera in
             (*search.known, *search.learned)}
    for camera in search.known:  # its design lies within the bounds: the sampler takes it as a design
        config = plan.config(first[camera], "runs")
        for key, low, high in zip(search.parameters, search.low, search.high):
            section, name = key.split(".", 1)
            value = getattr(getattr(config, section), name)
            if not low <= value <= high:
                raise PlanError(f"{where}.known: camera {camera!r} has {key} = {value!r}, outside the bounds "
                                f"[{low:g}, {high:g}]")
    for camera in search.learned:  # it learns a searched key, else it has no learned design to start from
        config = plan.config(first[camera], "runs")
        flags = [LEARNED_KEYS[key][0] for key in search.parameters if key in LEARNED_KEYS]
        if not any(getattr(getattr(config, flag.split(".")[0]), flag.split(".")[1]) for flag in flags):
            raise PlanError(f"{where}.learned: camera {camera!r} learns none of the searched keys "
                            f"({', '.join(search.parameters)}): nothing learned to start from")
    for camera in plan.cameras:
        if search.design_values(camera.name) is not None:
            raise PlanError(f"{where}.name: the plan's camera {camera.name!r} is named as a design of the search; "
                            "rename one of them")
    for values in corner_designs(search):
        cell = Cell(search.camera(values), search.light, plan.seeds[0], plan.fold_names()[0])
        try:
            config = plan.config(cell, "runs")
            check_config(config, "config")
        except ConfigError as error:
            raise PlanError(f"{where}: design {cell.camera} (a corner of the bounds): {error}") from None
        for key, value in zip(search.parameters, values):
            section, name = key.split(".", 1)
            if getattr(getattr(config, section), name) != value:
                raise PlanError(f"{where}.bounds.{key}: design {cell.camera} trains with {key} = "
                                f"{getattr(getattr(config, section), name)!r}, not {value!r}: a light's keys or --set "
                                "change it after the design's own; leave the key to the search")


def _seed_offset(camera: dict, source: str) -> int:
    offset = camera.get("seed_offset", 0)
    if offset < 0:
        raise PlanError(f"{source}: camera {camera['name']}.seed_offset: expected an integer >= 0, got {offset}")
    return offset


def _base_data(plan: Plan):
    """The data section of the plan's base config with the study's and the command line's overrides (what the folds
    are cut from), any placeholder left empty; a PlanError naming the key or file where it does not resolve."""
    unfilled = Cell("", "", 0, "")
    overrides = [fill_placeholders(text, unfilled) for text in [*plan.set, *cell_overrides(plan.overrides)]]
    try:
        return load_config([plan.base] if plan.base else None, overrides).data
    except ConfigError as error:
        raise PlanError(f"{plan.source}: {error}") from None


def fold_sizes(plan: Plan) -> list[dict]:
    """Per fold of the plan: {"fold", "train" (frames it trains on), "judged" (frames it is judged on), "labelled"
    (frames of the labelled splits: train_split + val_split)}, from the base config's data (file lists only; before
    ``max_train_images`` and ``max_val_images``). Without folds, one row "" of the train and val splits. A fold that
    judges no frame or trains on none is a PlanError naming it."""
    from warpsense.data import build_dataset, fold_frames

    data = _base_data(plan)
    rows = []
    try:
        if plan.folds == "none":
            train = len(build_dataset(data, data.train_split, train=True, seed=0))
            judged = len(build_dataset(data, data.val_split, train=False, seed=0))
            return [{"fold": "", "train": train, "judged": judged, "labelled": train + judged}]
        for fold in plan.fold_names():
            keys = dict(_assignment(text) for text in plan.fold_overrides(fold))
            train, held = fold_frames(dataclasses.replace(data, **keys))
            rows.append({"fold": fold, "train": len(train), "judged": len(held),
                         "labelled": len(train.sources[0]) + len(train.sources[1])})
    except DatasetError as error:
        where = f"study.folds = {plan.folds!r}" + (f", fold {fold}" if plan.folds != "none" else "")
        raise PlanError(f"{plan.source}: {where}: data: {error}") from None
    return rows


def _assignment(text: str) -> tuple[str, object]:
    """"data.key=value" as (key, the parsed value)."""
    return next(iter(parse_override(text)["data"].items()))


def fold_lines(rows: list[dict]) -> list[str]:
    """`fold_sizes`' rows in words: "fold block1: train 372 frames (79% of the labelled frames), judge 93 frames"."""
    return [f"{'fold ' + row['fold'] if row['fold'] else 'no folds (the train split; judged on val)'}: train "
            f"{row['train']} frames ({row['train'] / max(row['labelled'], 1):.0%} of the labelled frames), judge "
            f"{row['judged']} frames" for row in rows]


def _all_overrides(plan: Plan) -> list[str]:
    """Every override string of the plan: the study's, the cameras', the lights' and the command line's."""
    return [*plan.set, *(text for camera in plan.cameras for text in camera.set),
            *(text for light in plan.lights for text in light.set), *cell_overrides(plan.overrides)]


def _fold_sequences(plan: Plan, wanted: list) -> tuple[str, ...]:
    """The held-out sequences of a ``folds = "sequence"`` plan: ``wanted`` (study.sequences) or every sequence of
    the base config's labelled splits (train_split + val_split), checked against the frames."""
    where = f"{plan.source}: study.folds"
    data = _base_data(plan)  # the config's own errors (a bad --set, a missing data root) name their key or file
    try:
        names = sequence_names(data)
    except DatasetError as error:
        raise PlanError(f"{plan.source}: data: {error} (study.folds = \"sequence\" lists the labelled splits' "
                        "sequences)") from None
    if len(names) < 2:
        raise PlanError(f"{where}: the labelled splits ({data.train_split}, {data.val_split}) hold "
                        f"{len(names)} sequence(s) ({', '.join(names)}): a fold needs others to train on")
    if not all(isinstance(name, str) for name in wanted) or len(set(wanted)) != len(wanted):
        raise PlanError(f"{plan.source}: study.sequences: expected distinct sequence names, got {wanted!r}")
    for name in wanted:
        if name not in names:
            raise PlanError(f"{plan.source}: study.sequences: {name!r} holds no frame of the labelled splits "
                            f"({data.train_split}, {data.val_split}); sequences: {', '.join(names)}")
    chosen = tuple(wanted) or tuple(names)
    for name in chosen:
        if not name or not _plain(name):
            raise PlanError(f"{where}: sequence {name!r} cannot name a cell (no '/', '.' or spaces at the ends)")
    return chosen
