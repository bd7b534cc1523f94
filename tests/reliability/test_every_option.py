"""The bad-input corpus over every option (issue 61): cases GENERATED from the argument parser
(`warpsense.cli.build_parser`) for every option of every command and subcommand, and from the `Config` dataclasses
for every config key, one per kind of bad value that applies (missing value, wrong type, NaN, inf, negative, zero,
out of range, unknown choice, contradicting another option or key). Each must exit 2 with a one-line error naming
the option or key (argparse's usage block above its error line aside), without a traceback, and write nothing (each
runs in an empty temporary working directory, compared before and after).

`test_every_option_has_a_case` and `test_every_config_key_has_a_case` fail when an option or key has no case: a new
option whose value the generator cannot classify (a free string, an integer of unknown range) must be added to the
explicit tables below."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from tests.reliability.conftest import files_under
from warpsense import cli
from warpsense.commands.bench import seed_list
from warpsense.config import RETIRED, RETIRED_VALUES, Config, preset_names

# --------------------------------------------------------------------------------------------------------------------
# the parser, introspected


def _parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(command path, parser) for the top level and every command and subcommand."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, (*path, name))


def _options():
    """(command path, option name, action) for every option and positional argument (help and the subcommand
    choosers left out: they take no value)."""
    for path, parser in _parsers(cli.build_parser()):
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            name = max(action.option_strings, key=len) if action.option_strings else action.dest
            yield path, name, action


def _key(path, name) -> str:
    return " ".join([*path, name]).strip()


# A valid command line per command, to which a case adds its bad value: each is refused before the command's work
# starts. Cases run in an empty working directory; CHECKPOINT is a small checkpoint outside it.
CHECKPOINT = "<checkpoint>"
BASE = {
    (): [],
    ("train",): ["train", "--no-progress", "--set", "train.epochs=1", "--set", "train.warmup_epochs=0",
                 "--set", "train.max_steps_per_epoch=1", "--set", "data.scenes_train=2", "--set", "data.scenes_val=2",
                 "--set", "data.batch_size=2", "--set", "train.plots=false"],
    ("eval",): ["eval", "--checkpoint", CHECKPOINT, "--device", "cpu", "--limit", "1", "--no-progress"],
    ("bench",): ["bench", "--quick"],
    ("convert",): ["convert", "--no-progress", "--out", "converted", "no_such_raw.dng"],
    ("predict",): ["predict", CHECKPOINT, "no_such_raw.dng", "--out", "prediction.png", "--device", "cpu"],
    ("study", "run"): ["study", "run", "smoke", "--out", "study"],
    ("study", "status"): ["study", "status", "no_such_study"],
    ("study", "report"): ["study", "report", "no_such_study"],
    ("lens",): ["lens", "phone_68deg"],
    ("simulate",): ["simulate", "no_such_image.png", "--out", "simulated", "--config", preset_names()[0]],
    ("calibrate",): ["calibrate", "no_such_capture.dng"],
}
# options that a value of theirs needs beside it to be read at all
CONTEXT = {
    "eval --plot": ["--sweep"], "eval --latency-size": ["--latency"], "eval --latency-batch": ["--latency"],
    "study report --split": ["--plot", "report.png"],
    "bench --camvid": ["--suite", "accuracy"],
    "study run --slurm-partition": ["--executor", "slurm"], "study run --slurm-time": ["--executor", "slurm"],
    "study run --gpus-per-cell": ["--executor", "slurm"], "study run --array-parallelism": ["--executor", "slurm"],
    "study run --slurm-option": ["--executor", "slurm"], "study run --wait": ["--executor", "slurm"],
}
# the least valid value of integer options whose argparse type does not say it (plain `int`); an option of that type
# missing here fails `test_every_option_has_a_case`
INT_MINIMUM = {"study run --slurm-time": 1, "study run --gpus-per-cell": 0, "study run --array-parallelism": 1}

# The allow-list: options that take any string (a path, a name, a config override), where the generator has no bad
# value to draw. Each lists its own cases instead: (label, the arguments, what the error line must name). A path
# case is a path that cannot be used (missing, a folder for a file, a file for a folder, in a missing folder).
FREE_STRINGS = {
    "train --config": [("missing_file", ["--config", "no_such_file.toml"], ("no_such_file.toml",))],
    "train --set": [("no_equals", ["--set", "train.epochs"], ("train.epochs",)),
                    ("unknown_key", ["--set", "train.epoch=3"], ("train.epoch",))],
    "train --resume-dir": [("missing_run", ["--resume-dir", "no_such_run"], ("no_such_run",))],
    "eval --checkpoint": [("missing_file", ["--checkpoint", "no_such.safetensors"], ("no_such.safetensors",))],
    "eval --data-root": [("missing_folder", ["--data", "camvid", "--data-root", "no_such_root"], ("no_such_root",))],
    "eval --split": [("unknown_split", ["--split", "no_such_split"], ("no_such_split",))],
    "eval --json": [("missing_folder", ["--json", "no_dir/m.json"], ("--json",)),
                    ("a_folder", ["--json", "."], ("--json",))],
    "eval --plot": [("missing_folder", ["--plot", "no_dir/p.png"], ("--plot",))],
    "bench --json": [("missing_folder", ["--json", "no_dir/b.json"], ("--json",))],
    "bench --plot": [("missing_folder", ["--plot", "no_dir/b.png"], ("--plot",))],
    "bench --camvid": [("missing_folder", ["--camvid", "no_such_camvid"], ("no_such_camvid",))],
    "bench --plan": [("missing_plan", ["--suite", "study", "--out", "suite", "--plan", "no_such_plan"],
                      ("no_such_plan",)), ("other_suite", ["--plan", "smoke"], ("--plan",))],
    "bench --out": [("without_plan", ["--suite", "study", "--out", "suite"], ("--plan",)),
                    ("other_suite", ["--out", "suite"], ("--out",))],
    "bench --gpus": [("not_ids", ["--suite", "study", "--plan", "smoke", "--out", "suite", "--gpus", "one,two"],
                      ("--gpus",)),
                     ("absent_gpu", ["--suite", "study", "--plan", "smoke", "--out", "suite", "--gpus", "97"],
                      ("--gpus 97",))],  # no CUDA here, or no GPU 97 on a GPU machine
    "bench --set": [("unknown_key", ["--suite", "study", "--plan", "smoke", "--out", "suite", "--set",
                                     "train.epoch=3"], ("train.epoch",)),
                    ("unknown_train_key", ["--suite", "train", "--set", "model.sqeeze=true"], ("model.sqeeze",)),
                    ("other_suite", ["--suite", "kernels", "--set", "model.squeeze=true"], ("--set",))],
    "convert inputs": [("missing_file", [], ("no_such_raw.dng",))],  # the base names a raw file that does not exist
    "convert --out": [("a_file", ["--out", "file.txt"], ("--out",))],
    "predict checkpoint": [("missing_file", [], ("<checkpoint>",))],  # replaced by a missing file below
    "predict input": [("missing_file", [], ("no_such_raw.dng",))],
    "predict --out": [("missing_folder", ["--out", "no_dir/p.png"], ("--out",))],
    "study run plan": [("missing_plan", [], ("no_such_plan",))],  # replaced below
    "study run --out": [("a_file", ["--out", "file.txt"], ("file.txt",))],
    "study run --set": [("unknown_key", ["--set", "train.epoch=3"], ("train.epoch",))],
    "study run --cells": [("matches_nothing", ["--cells", "no/such*"], ("no/such*",))],
    "study run --cell": [("unknown_cell", ["--cell", "no/such/0"], ("no/such/0",))],
    "study run --gpus": [("not_ids", ["--gpus", "one,two"], ("--gpus",)), ("empty", ["--gpus", ","], ("--gpus",)),
                         ("absent_gpu", ["--gpus", "97"], ("--gpus 97",))],
    "study run --reuse": [("missing_study", ["--reuse", "no_such_study"], ("no_such_study",))],
    "study run --slurm-partition": [("bad_name", ["--slurm-partition", "a b"], ("--slurm-partition",))],
    "study run --slurm-option": [("no_key", ["--slurm-option", "=5"], ("--slurm-option",))],
    "study status study_dir": [("missing_study", [], ("no_such_study",))],
    "study report study_dir": [("missing_study", [], ("no_such_study",))],
    "study report --json": [("missing_folder", ["--json", "no_dir/r.json"], ("--json",))],
    "study report --plot": [("missing_folder", ["--plot", "no_dir/r.png"], ("--plot",))],
    "study report --split": [("unknown_split", ["--split", "no_such_split"], ("no_such_study",))],  # the study first
    "lens lens": [("missing_lens", [], ("no_such_lens",))],  # replaced below
    "lens --plot": [("missing_folder", ["--plot", "no_dir/l.png"], ("--plot",))],
    "eval --latency-size": [("not_hxw", ["--latency-size", "192"], ("--latency-size",)),
                            ("zero", ["--latency-size", "0x640"], ("--latency-size",)),
                            ("negative", ["--latency-size", "-1x640"], ("--latency-size",)),
                            ("nan", ["--latency-size", "nanxnan"], ("--latency-size",)),
                            # a traceback from the fixed ISP's reflection padding once the checkpoint had loaded
                            ("one_pixel_side", ["--latency-size", "1x640"], ("--latency-size", ">= 2"))],
    "simulate images": [("missing_file", [], ("no_such_image.png",))],
    "simulate --config": [("missing_file", ["--config", "no_such_file.toml"], ("no_such_file.toml",))],
    "simulate --set": [("unknown_key", ["--set", "train.epoch=3"], ("train.epoch",))],
    "simulate --checkpoint": [("with_config", ["--checkpoint", "no_such.safetensors"], ("--checkpoint",))],
    "simulate --out": [("a_file", ["--out", "file.txt"], ("--out",))],
    "calibrate captures": [("missing_file", [], ("no_such_capture.dng",))],
    "calibrate --json": [("missing_folder", ["--json", "no_dir/c.json"], ("--json",)),
                         ("a_folder", ["--json", "."], ("--json",))],
    "calibrate --out": [("missing_folder", ["--out", "no_dir/p.toml"], ("--out",)),
                        ("not_toml", ["--out", "preset.txt"], ("--out",))],
    "calibrate --base": [("unknown_preset", ["--out", "p.toml", "--base", "no_such_preset"], ("no_such_preset",)),
                         ("without_out", ["--base", "camvid"], ("--base",))],
    "calibrate --plot": [("missing_folder", ["--plot", "no_dir/c.png"], ("--plot",))],
    "calibrate --dark": [("without_series", ["--dark", "d.dng"], ("--dark",))],
}
# positionals whose free-string case replaces the base's value instead of adding arguments
REPLACE = {"predict checkpoint": (CHECKPOINT, "no_such.safetensors"), "study run plan": ("smoke", "no_such_plan"),
           "lens lens": ("phone_68deg", "no_such_lens")}
# options that take no value and whose only misuse is a value given to them (`--flag=yes`), or none at all
NO_VALUE = {"--version": "prints the version and exits 0 by design", "study run --worker": "internal (the pool's)"}
# values valid alone that contradict another option: (label, arguments, names)
CONTRADICTIONS = {
    "train --extend": [("without_resume", ["--extend", "2"], ("--extend",))],
    "train --resume-dir": [("two_runs", ["--resume", "--resume-dir", "no_such_run"], ("--resume",))],
    "eval --plot": [("without_sweep", ["--plot", "p.png"], ("--sweep",))],
    "study run --executor": [("slurm_plan_only", ["--executor", "slurm", "--plan-only"], ("--plan-only",))],
    "study run --slurm-time": [("local_executor", ["--slurm-time", "5"], ("--slurm-time",))],
    "bench --seeds": [("other_suite", ["--suite", "kernels", "--seeds", "0,1"], ("--seeds",))],
}
LIST_TYPES = {
    seed_list: [("wrong_type", "a,b"), ("nan", "nan"), ("negative", "-1"), ("duplicate", "0,0"), ("float", "1.5")],
}


def _value_cases(key: str, option: str, action) -> list[tuple[str, list[str], tuple[str, ...]]]:
    """The generated cases of one option: (kind, arguments, names)."""
    if action.nargs == 0 or isinstance(action, argparse._StoreConstAction):
        return [("given_a_value", [f"{option}=yes"], (option,))]
    cases = []
    if action.option_strings:
        cases.append(("missing_value", [option], (option,)))
    if action.choices is not None:
        cases.append(("unknown_choice", [option, "no_such_choice"], (option,)))
    if action.type in LIST_TYPES:
        cases += [(kind, [option, value], (option,)) for kind, value in LIST_TYPES[action.type]]
    elif action.type is int or getattr(action.type, "__name__", "") == "integer":
        minimum = getattr(action.type, "minimum", INT_MINIMUM.get(key))
        cases += [("wrong_type", [option, "many"], (option,)), ("nan", [option, "nan"], (option,)),
                  ("inf", [option, "inf"], (option,)), ("float", [option, "1.5"], (option,))]
        if minimum is not None:
            cases.append(("below_minimum", [option, str(minimum - 1)], (option,)))
            cases.append(("negative", [option, "-3"], (option,)))
            if minimum > 0:
                cases.append(("zero", [option, "0"], (option,)))
    return cases


def _cli_cases():
    for path, option, action in _options():
        key = _key(path, option)
        if option in NO_VALUE or key in NO_VALUE:
            continue
        for kind, arguments, names in _value_cases(key, option, action):
            yield key, kind, path, arguments, names
        for kind, arguments, names in [*FREE_STRINGS.get(key, []), *CONTRADICTIONS.get(key, [])]:
            yield key, kind, path, arguments, names


CLI_CASES = list(_cli_cases())
# defects the corpus found in modules this corpus does not own, open: the case is expected to fail until fixed
KNOWN_DEFECTS: dict = {}  # (option or key, case) -> why it is accepted today: strict expected failures


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A small checkpoint of the default config (outside the cases' working directories)."""
    from warpsense.config import load_config
    from warpsense.system import build_system
    from warpsense.system.checkpoint import save_checkpoint

    path = tmp_path_factory.mktemp("checkpoint") / "tiny.safetensors"
    config = load_config(None, ["model.width=4"])
    save_checkpoint(path, build_system(config, 11), config.to_dict(), {"epoch": 0, "num_classes": 11})
    return path


class Accepted(Exception):
    """A bad value reached the command's work: the case was accepted."""


@pytest.fixture
def refuse_work(monkeypatch):
    """The commands' long work raises `Accepted` instead of running (minutes of benchmarks or a study's training)."""
    import warpsense.bench.runner
    import warpsense.study.runner
    import warpsense.study.slurm
    import warpsense.study.worker

    def accepted(*args, **kwargs):
        raise Accepted("the bad value was accepted")

    monkeypatch.setattr(warpsense.bench.runner, "run_bench", accepted)
    monkeypatch.setattr(warpsense.study.runner, "run_cells", accepted)
    monkeypatch.setattr(warpsense.study.worker, "cell_worker", accepted)
    monkeypatch.setattr(warpsense.study.slurm, "submit_study", accepted)


def assert_refused(capsys, cwd, argv: list[str], names: tuple[str, ...]) -> None:
    """``warpsense argv`` exits 2 with one error line naming ``names`` (argparse's usage block before it aside), no
    traceback, and nothing written under ``cwd``."""
    before = files_under(cwd)
    try:
        code = cli.main(argv)
    except SystemExit as exit_:
        code = exit_.code
    error = capsys.readouterr().err.strip()
    assert code == 2, f"exit {code} for {argv}: {error}"
    assert "Traceback" not in error, error
    lines = error.splitlines()
    if lines and lines[0].startswith("usage:"):  # argparse: the usage block, then its one error line
        lines = [line for line in lines if ": error: " in line]
    assert len(lines) == 1, f"not one error line for {argv}: {error}"
    for name in names:
        assert name in lines[0], f"{name!r} not named in: {lines[0]}"
    assert files_under(cwd) == before, f"written by {argv}: {sorted(files_under(cwd) - before)}"


@pytest.mark.parametrize("key, kind, path, arguments, names",
                         [pytest.param(*case, id=f"{case[0]}:{case[1]}", marks=[pytest.mark.xfail(
                             reason=KNOWN_DEFECTS[case[:2]], strict=True)] if case[:2] in KNOWN_DEFECTS else [])
                          for case in CLI_CASES])
def test_bad_option_values(key, kind, path, arguments, names, checkpoint, refuse_work, tmp_path, monkeypatch,
                           capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file.txt").write_text("a file where a folder belongs\n")
    base = [str(checkpoint) if part == CHECKPOINT else part for part in BASE[path]]
    if key in REPLACE:
        old, new = REPLACE[key]
        base = [new if part == (str(checkpoint) if old == CHECKPOINT else old) else part for part in base]
        names = (new,)
    context = [] if key in CONTRADICTIONS and kind in {k for k, _, _ in CONTRADICTIONS[key]} else CONTEXT.get(key, [])
    if not path:  # top-level options go before a command
        argv = [*arguments, "lens", "phone_68deg"]
    elif arguments and arguments[0].startswith("-"):
        argv = [*base, *context, *arguments] if kind != "missing_value" else [*base, *context, *arguments]
    else:
        argv = [*base, *arguments]
    if kind == "missing_value" and path:
        argv = [*base, *context, arguments[0]]  # the option last, with no value after it
    assert_refused(capsys, tmp_path, argv, names)


@pytest.mark.parametrize("key", sorted({_key(path, option) for path, option, _ in _options()}))
def test_every_option_has_a_case(key):
    """A new option needs a case: one the generator draws from its type and choices, or an entry in FREE_STRINGS
    (what a path or name it takes cannot be), INT_MINIMUM or NO_VALUE."""
    option = key.split()[-1]
    assert key in {case[0] for case in CLI_CASES} or key in NO_VALUE or option in NO_VALUE, \
        f"{key}: no bad-value case; add it to FREE_STRINGS (a free string or path), INT_MINIMUM or NO_VALUE"
    action = next(a for p, o, a in _options() if _key(p, o) == key)
    takes_text = action.nargs != 0 and not isinstance(action, argparse._StoreConstAction) and action.choices is None
    if takes_text and action.type in (None, str):
        assert key in FREE_STRINGS, f"{key} takes any string: list its path or name cases in FREE_STRINGS"
    if action.type is int:
        assert key in INT_MINIMUM, f"{key} is a plain int: give its least valid value in INT_MINIMUM"


# --------------------------------------------------------------------------------------------------------------------
# every config key, through --set


def _config_keys():
    for section in dataclasses.fields(Config):
        for spec in dataclasses.fields(section.default_factory):
            yield f"{section.name}.{spec.name}", spec


WRONG = {"bool": '"yes"', "int": '"many"', "float": '"x"', "str": "5"}
# keys that take any string (names, paths): their own bad values, each refused with the key named
FREE_STRING_KEYS = {
    "run.name": [("path", "../escape"), ("empty", '""')],
    "run.output_dir": [("a_file", '"file.txt"')],
    "data.root": [("missing_folder", '"no_such_root"', ["data.dataset=camvid"])],  # names the path
    "data.classes_file": [("missing_file", '"no_such_classes.toml"')],
    "data.train_split": [("unknown_split", '"no_such_split"')],
    "data.val_split": [("unknown_split", '"no_such_split"')],
    "data.paste_classes": [("unknown_class", '"no_such_class"')],
    "data.holdout_prefix": [("both_holdouts", '"seq"', ["data.holdout_sequence=a"])],
    "data.holdout_sequence": [("a_path", '"a/b"')],
    "optics.lens": [("missing_lens", '"no_such_lens"', ["optics.enabled=true"])],
    "cfa.candidates": [("unknown_filter", '"RGBX"')],
    "loss.teacher": [("missing_file", '"no_such.safetensors"', ["loss.distill_weight=0.5"])],
}
# keys with no range whose every finite value is valid: a seed, a logit (its NaN and inf cases are generated)
ANY_NUMBER = {"photons.eval_seed": "a seed", "noise.eval_seed": "a seed", "exposure.gain_logit": "a logit",
              "cfa.init_logit": "a logit"}
# keys valid alone that contradict another key: (label, overrides, names)
KEY_CONTRADICTIONS = {
    "train.warmup_epochs": [("over_epochs", ["train.epochs=2", "train.warmup_epochs=3"], ("train.warmup_epochs",))],
    "data.scale_min": [("over_max", ["data.scale_min=2.0", "data.scale_max=1.5"], ("data.scale_min",))],
    "train.cuda_graph": [("self_capturing", ["train.cuda_graph=true", 'train.compile="reduce-overhead"'],
                          ("train.cuda_graph",))],
    "train.micro_batch": [("cuda_graph", ["train.micro_batch=2", "train.cuda_graph=true"], ("train.micro_batch",))],
    "optics.f_number_min": [("over_max", ["optics.f_number_min=8", "optics.f_number_max=2"], ("optics.f_number_min",))],
    "optics.exposure_ms_min": [("over_max", ["optics.exposure_ms_min=20", "optics.exposure_ms_max=5"],
                                ("optics.exposure_ms_min",))],
    "loss.distill_weight": [("without_teacher", ["loss.distill_weight=0.5"], ("loss.teacher",))],
}


def _config_cases():
    for key, spec in _config_keys():
        cases = [("wrong_type", [f"{key}={WRONG[spec.type]}"], (key,))]
        choices = spec.metadata.get("choices")
        if choices:
            cases.append(("unknown_choice", [f'{key}="no_such_choice"'], (key,)))
        if spec.type == "float":
            cases += [(kind, [f"{key}={value}"], (key,)) for kind, value in (("nan", "nan"), ("inf", "inf"),
                                                                              ("minus_inf", "-inf"))]
        if spec.type == "int":
            cases += [("nan", [f"{key}=nan"], (key,)), ("float", [f"{key}=1.5"], (key,))]
        minimum, maximum, exclusive = spec.metadata.get("range", (None, None, False))
        if minimum is not None:
            below = minimum if exclusive else (minimum - 1 if spec.type == "int" else minimum - 0.5 * max(minimum, 1))
            cases.append(("below_minimum", [f"{key}={below}"], (key,)))
            if minimum >= 0:
                cases.append(("negative", [f"{key}=-3"], (key,)))
            if minimum > 0 or exclusive:
                cases.append(("zero", [f"{key}=0"], (key,)))
        if maximum is not None:
            above = maximum * 2 + 1
            cases.append(("above_maximum", [f"{key}={int(above) if spec.type == 'int' else above}"], (key,)))
        for kind, value, *extra in FREE_STRING_KEYS.get(key, []):
            path_case = kind in ("missing_folder", "missing_file")  # the error names the path
            cases.append((kind, [*(extra[0] if extra else []), f"{key}={value}"],
                          (value.strip('"'),) if path_case else (key,)))
        cases += KEY_CONTRADICTIONS.get(key, [])
        for kind, overrides, names in cases:
            yield key, kind, overrides, names


CONFIG_CASES = list(_config_cases())
# retired keys and values (`warpsense.config.RETIRED`, `RETIRED_VALUES`): refused naming them and where to read why
CONFIG_CASES += [(key, "retired", [f"{key}=1"], (key, "docs/records/history.md")) for key in RETIRED]
CONFIG_CASES += [(key, "retired_value", [f'{key}="{value}"'], (key, repr(value), "docs/records/history.md"))
                 for key, value in RETIRED_VALUES]


@pytest.mark.parametrize("key, kind, overrides, names",
                         [pytest.param(*case, id=f"{case[0]}:{case[1]}", marks=[pytest.mark.xfail(
                             reason=KNOWN_DEFECTS[case[:2]], strict=True)] if case[:2] in KNOWN_DEFECTS else [])
                          for case in CONFIG_CASES])
def test_bad_config_values(key, kind, overrides, names, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file.txt").write_text("a file where a folder belongs\n")
    sets = [part for text in overrides for part in ("--set", text)]
    assert_refused(capsys, tmp_path, [*BASE[("train",)], *sets], names)


@pytest.mark.parametrize("key", [key for key, _ in _config_keys()])
def test_every_config_key_has_a_case(key):
    """A new key needs a case beyond its wrong type: a range or choices in its `_field`, or an entry in
    FREE_STRING_KEYS (a free string), ANY_NUMBER (every finite number valid) or KEY_CONTRADICTIONS; a bool's
    misuse is its wrong type."""
    spec = dict(_config_keys())[key]
    kinds = {kind for k, kind, _, _ in CONFIG_CASES if k == key} - {"wrong_type"}
    if spec.type == "bool":
        assert "wrong_type" in {kind for k, kind, _, _ in CONFIG_CASES if k == key}
        return
    if spec.type == "str":
        assert kinds, f"{key} takes any string: list its bad values in FREE_STRING_KEYS"
        return
    ranged = {"below_minimum", "above_maximum"} & kinds
    assert ranged or key in ANY_NUMBER or key in KEY_CONTRADICTIONS, \
        f"{key}: no range in its _field; give it one, or list it in ANY_NUMBER with the reason"
