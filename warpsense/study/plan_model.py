"""A study plan as typed data: its cameras, light levels and sweeps, its folds, its cells (camera x light x seed,
and x fold), which of them ``--cell`` and ``--cells`` name, and the config each cell trains with. Reading a plan file
into one is `warpsense.study.plan.load_plan`."""

from __future__ import annotations

import dataclasses
import fnmatch
import json
from dataclasses import dataclass
from pathlib import Path

from warpsense.config import Config, load_config
from warpsense.study.search_space import SearchSpec
from warpsense.study.sequential import SequentialRule


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


def is_study_override(text: str) -> bool:
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
    return [text for text in overrides if not is_study_override(text)]


def plain_name(text: str) -> bool:
    """Whether ``text`` can be part of a cell id and a run directory's name: no '/', no '.', no spaces at the ends."""
    return "/" not in text and "." not in text and text == text.strip()
