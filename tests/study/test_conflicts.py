"""What a plan says is what runs: two tables of a plan that set one config key of a cell to different values (a
sweep's grid and a light, the study's set and a camera's preset, a camera's set and a light, a sweep's set and its
grid) are refused in one line naming the key and both tables, before anything is written; so is a table that sets a
key the study sets per cell. The base preset and the command line's --set override as documented."""

from pathlib import Path

import pytest

from warpsense.cli import main
from warpsense.resources import CONFIG_DIR
from warpsense.study import load_plan

SMOKE = (CONFIG_DIR / "studies" / "smoke.toml").read_text()


def _plan(tmp_path: Path, extra: str = "", study_set: str = "") -> Path:
    text = SMOKE
    if study_set:
        text = text.replace('set = ["data.scenes_train=96"', f'set = [{study_set}, "data.scenes_train=96"')
    path = tmp_path / "plan.toml"
    path.write_text(text + extra)
    return path


@pytest.mark.parametrize(("extra", "study_set", "message"), [
    ('[[sweep]]\nname = "adc"\ngrid = { "quantize.bits" = [8, 12] }\n', "",
     "quantize.bits is 8 in sweep 'adc''s grid and 10 in light 'night'"),
    ('[[camera]]\nname = "eight"\nset = ["quantize.bits=8"]\n', "",
     "quantize.bits is 8 in camera 'eight''s set and 10 in light 'night'"),
    ('[[sweep]]\nname = "g"\nset = ["cfa.pattern=\\"RCCB\\""]\ngrid = { "cfa.pattern" = ["RGGB", "BGGR"] }\n', "",
     "cfa.pattern is \"RCCB\" in sweep 'g''s set and \"RGGB\" in sweep 'g''s grid"),
    ('[[camera]]\nname = "preset"\npreset = "PRESET"\n', '"cfa.temperature_end=0.5"',
     "cfa.temperature_end is 0.1 in camera 'preset''s preset 'PRESET' and 0.5 in [study].set"),
    ('[[camera]]\nname = "seeded"\nset = ["run.seed=5"]\n', "",
     "camera 'seeded''s set sets run.seed, which the study sets for each cell"),
])
def test_conflicting_tables_are_one_line_errors_with_nothing_written(tmp_path, extra, study_set, message, capsys):
    preset = tmp_path / "fixed.toml"
    preset.write_text("[cfa]\ntemperature_end = 0.1\n")
    plan = _plan(tmp_path, extra.replace("PRESET", str(preset)), study_set)
    out = tmp_path / "study"
    assert main(["study", "run", str(plan), "--out", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and str(plan) in error and message.replace("PRESET", str(preset)) in error
    assert "set it in one table" in error or "leave it out" in error
    assert not out.exists()


def test_equal_values_the_base_and_the_command_line_are_not_conflicts(tmp_path):
    # the same value in two tables says one thing; the study's base is every cell's recipe, meant to be overridden
    plan = load_plan(_plan(tmp_path, '[[camera]]\nname = "ten"\nset = ["quantize.bits=10"]\n',
                           '"model.width=8"'))
    cell = next(c for c in plan.cells() if c.camera == "ten")
    assert plan.config(cell, tmp_path).quantize.bits == 10 and plan.config(cell, tmp_path).model.width == 8
    # the command line changes every cell, last (recorded in the study's plan.json as its overrides)
    plan = load_plan(_plan(tmp_path), ["quantize.bits=12", "cfa.pattern=\"BGGR\""])
    assert {plan.config(c, tmp_path).quantize.bits for c in plan.cells()} == {12}


def test_shipped_plans_have_no_conflicts():
    from warpsense.study.conflicts import check_conflicts
    from warpsense.study.plan import study_names

    for name in study_names():
        if name.startswith("camvid") and not Path(load_config_root(name)).is_dir():
            continue
        check_conflicts(load_plan(name))


def load_config_root(name: str) -> str:
    import tomllib

    from warpsense.config import load_config

    base = tomllib.loads((CONFIG_DIR / "studies" / f"{name}.toml").read_text())["study"].get("base") or None
    return load_config(base).data.root or "."
