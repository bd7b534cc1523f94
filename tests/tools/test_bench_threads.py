"""tools/bench_threads.py: the settings it compares set only the OpenMP variables they name, and a wrong one is
refused before any run starts."""

import pytest


@pytest.fixture
def tool(load_tool):
    return load_tool("bench_threads")


def test_settings_name_the_openmp_variables_they_change(tool):
    assert tool.SETTINGS["default"] == {}
    assert tool.SETTINGS["passive"] == {"OMP_WAIT_POLICY": "PASSIVE"}
    assert tool.SETTINGS["active"] == {"OMP_WAIT_POLICY": "ACTIVE"}
    assert tool.SETTINGS["one"] == {"OMP_NUM_THREADS": "1"}


def test_an_unknown_setting_is_a_usage_error(tool, capsys):
    with pytest.raises(SystemExit) as exit_info:
        tool.main(["--settings", "default,spinny"])
    assert exit_info.value.code == 2 and "unknown 'spinny'" in capsys.readouterr().err
