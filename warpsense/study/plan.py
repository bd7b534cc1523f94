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
made per fold. A sweep's point is a camera like the others (crossed with lights, folds and seeds; the reference may
be one), named ``<name>_<label><value>_...`` in the grid's key order (``grid_f1p4_t30``): camera names hold no '.',
which separates a run directory's parts, so a value's decimal point is written ``p`` and a minus sign ``m``. Unknown
keys, wrong types, duplicate or unknown names, folds that hold no frame, a dataset without sequence names and configs
that do not resolve are one-line `PlanError`s naming the plan file and key, found before anything is written.

The plan as typed data (`Plan`, `Cell`, the cameras, lights and sweeps) is `warpsense.study.plan_model`, its tables'
checks `warpsense.study.plan_tables`, its folds' frames `warpsense.study.folds`; this module reads a plan file and puts
them together (`load_plan`), and every name the study's other modules take from a plan is importable from here.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from warpsense.choices import LIGHT_LEVELS
from warpsense.config import ConfigError, read_toml
from warpsense.data import DatasetError, build_dataset
from warpsense.resources import CONFIG_DIR, shipped_studies
from warpsense.study.conflicts import check_conflicts
from warpsense.study.folds import fold_lines, fold_sequences, fold_sizes
from warpsense.study.keys import LEARNED_KEYS, value_label
from warpsense.study.plan_model import (
    BLOCK_FOLD,
    FOLDS,
    CameraSpec,
    Cell,
    LightSpec,
    Plan,
    PlanError,
    SweepSpec,
    cell_overrides,
    fill_placeholders,
)
from warpsense.study.plan_tables import (
    CAMERA_KEYS,
    LIGHT_KEYS,
    STUDY_KEYS,
    check_names,
    check_table,
    optional_float,
    point_overrides,
    search_spec,
    seed_offset,
    sequential_rule,
    sequential_seeds,
    string_list,
    study_overrides,
    sweep_spec,
)
from warpsense.study.search_space import corner_designs

__all__ = ["BLOCK_FOLD", "FOLDS", "CameraSpec", "Cell", "LightSpec", "Plan", "PlanError", "SweepSpec", "cell_overrides",
           "fill_placeholders", "fold_lines", "fold_sizes", "load_plan", "study_names", "value_label"]


study_names = shipped_studies
"""The plans shipped in configs/studies/ (one definition, in warpsense.resources, which the CLI's help also asks)."""


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
    study = check_table(study_overrides(study, overrides, source), STUDY_KEYS, f"{source}: study",
                        ("seeds", "reference"))
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
    cameras = [check_table(c, CAMERA_KEYS, f"{source}: camera[{i}]", ("name",)) for i, c in enumerate(cameras)]
    lights = [check_table(x, LIGHT_KEYS, f"{source}: light[{i}]", ("name",)) for i, x in enumerate(lights)]
    check_names(cameras, f"{source}: camera")
    sweeps = [sweep_spec(table, f"{source}: sweep[{i}]") for i, table in enumerate(sweep_tables)]
    check_names([{"name": sweep.name} for sweep in sweeps], f"{source}: sweep")  # before its points, named after it
    check_names([*cameras, *({"name": camera} for sweep in sweeps for camera, _ in sweep.points)], f"{source}: camera",
           "a [[camera]] or another sweep's point")
    cameras += [{"name": camera, "preset": sweep.preset, "set": [*sweep.set, *point_overrides(sweep, values)]}
                for sweep in sweeps for camera, values in sweep.points]
    check_names(lights, f"{source}: light")
    seeds = study["seeds"]
    if not seeds or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in seeds) \
            or len(set(seeds)) != len(seeds):
        raise PlanError(f"{source}: study.seeds: expected distinct integers >= 0, got {seeds!r}")
    rule = sequential_rule(study, source, 2)  # the rule's own keys here; its first look's pairs once folds are known
    if rule is not None:
        seeds = sequential_seeds(seeds, rule, source)
    search = search_spec(data.get("search", []), source, [x["name"] for x in lights], [c["name"] for c in cameras],
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
        set=string_list(study.get("set", []), f"{source}: study.set"), seeds=tuple(seeds),
        reference=study["reference"],
        cameras=tuple(CameraSpec(c["name"], c.get("preset", ""),
                                 string_list(c.get("set", []), f"{source}: camera {c['name']}.set"),
                                 seed_offset(c, source)) for c in cameras),
        lights=tuple(LightSpec(x["name"], optional_float(x.get("full_well_electrons")),
                               optional_float(x.get("read_electrons")), x.get("bits", 10), tuple(x.get("cameras", [])),
                               x.get("scene", ""), optional_float(x.get("analog_gain")),
                               string_list(x.get("set", []), f"{source}: light {x['name']}.set")) for x in lights),
        overrides=tuple(overrides), folds=study.get("folds", "none"), sweeps=tuple(sweeps),
        blocks=study.get("blocks", 5), block_buffer=study.get("block_buffer", 30), sequential=rule, search=search)
    if plan.folds == "sequence":
        plan = dataclasses.replace(plan, sequences=fold_sequences(plan, study.get("sequences", [])))
    elif plan.folds == "blocks":
        fold_sizes(plan)  # every fold judges and trains on frames, else a PlanError naming it
    elif any("{fold}" in text for text in _all_overrides(plan)):
        raise PlanError(f"{source}: {{fold}} in a set stands for a cell's fold: it needs study.folds = \"blocks\" "
                        f"or \"sequence\"")
    if rule is not None:
        sequential_rule(study, source, len(plan.fold_names()))
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


def _all_overrides(plan: Plan) -> list[str]:
    """Every override string of the plan: the study's, the cameras', the lights' and the command line's."""
    return [*plan.set, *(text for camera in plan.cameras for text in camera.set),
            *(text for light in plan.lights for text in light.set), *cell_overrides(plan.overrides)]
