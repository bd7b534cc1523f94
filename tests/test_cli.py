import subprocess
import sys

import pytest

import warpsense
from warpsense.cli import build_parser, main


def test_import_and_version(capsys):
    assert warpsense.__version__
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert warpsense.__version__ in capsys.readouterr().out


def test_help_lists_commands(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for command in ("train", "eval", "bench", "convert", "predict"):
        assert command in out


@pytest.mark.parametrize("command,option", [("train", "--set"), ("eval", "--checkpoint"), ("bench", "--quick"),
                                            ("convert", "--out"), ("predict", "--out")])
def test_subcommand_help_documents_options(capsys, command, option):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    assert option in capsys.readouterr().out


def test_bad_config_is_one_line_error_nonzero(capsys):
    assert main(["train", "--set", "train.epoch=1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("warpsense train: error:") and "train.epoch" in err and "\n" not in err


def test_console_entry_point_runs():
    result = subprocess.run([sys.executable, "-m", "warpsense", "--help"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and "convert" in result.stdout
    assert build_parser().prog == "warpsense"
