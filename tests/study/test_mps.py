"""The study pool's CUDA MPS daemon, against a stand-in `nvidia-cuda-mps-control` that records how it was called."""

import os
import stat
from pathlib import Path

import pytest

from warpsense.study import mps, runner
from warpsense.study.mps import MPSError, mps_daemon, wanted

FAKE = """#!/bin/sh
# records the arguments, the pipe directory and stdin; exits with $FAKE_MPS_EXIT
echo "args=$* pipe=$CUDA_MPS_PIPE_DIRECTORY log=$CUDA_MPS_LOG_DIRECTORY" >> "$FAKE_MPS_RECORD"
if [ "$*" = "" ]; then cat >> "$FAKE_MPS_RECORD"; fi
[ -n "$FAKE_MPS_EXIT" ] && echo "cannot start" >&2 && exit "$FAKE_MPS_EXIT"
exit 0
"""


@pytest.fixture
def fake_control(tmp_path, monkeypatch) -> Path:
    folder = tmp_path / "bin"
    folder.mkdir()
    program = folder / mps.CONTROL
    program.write_text(FAKE)
    program.chmod(program.stat().st_mode | stat.S_IEXEC)
    record = tmp_path / "calls.txt"
    monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("FAKE_MPS_RECORD", str(record))
    monkeypatch.delenv("FAKE_MPS_EXIT", raising=False)
    return record


def test_wanted_by_mode_and_cells_per_gpu(fake_control, monkeypatch):
    assert wanted("auto", 2) and not wanted("auto", 1) and wanted("on", 1) and not wanted("off", 4)
    with pytest.raises(ValueError, match="--mps must be one of auto, on, off"):
        wanted("maybe", 2)
    monkeypatch.setenv("PATH", "/nonexistent")
    assert not wanted("auto", 4)  # no MPS on this machine: the pool runs without it
    with pytest.raises(MPSError, match="--mps on: nvidia-cuda-mps-control is not on the PATH"):
        wanted("on", 2)


def test_daemon_started_with_its_own_folders_and_quit(fake_control):
    with mps_daemon(True) as environment:
        pipe = Path(environment["CUDA_MPS_PIPE_DIRECTORY"])
        assert pipe.is_dir() and Path(environment["CUDA_MPS_LOG_DIRECTORY"]).is_dir()
        worker = runner.worker_environment("1", 2, environ={}, cores=8, extra=environment)
        assert worker["CUDA_MPS_PIPE_DIRECTORY"] == str(pipe) and worker["CUDA_VISIBLE_DEVICES"] == "1"
    calls = fake_control.read_text().splitlines()
    assert calls == [f"args=-d pipe={pipe} log={pipe.parent / 'log'}", f"args= pipe={pipe} log={pipe.parent / 'log'}",
                     "quit"]
    assert not pipe.parent.exists()  # the folder goes with the daemon
    with mps_daemon(False) as environment:
        assert environment == {}


def test_daemon_that_cannot_start_is_one_error(fake_control, monkeypatch):
    monkeypatch.setenv("FAKE_MPS_EXIT", "3")
    with pytest.raises(MPSError, match="nvidia-cuda-mps-control -d exited 3: cannot start"):
        with mps_daemon(True):
            pass


def test_pool_refuses_mps_on_without_the_daemon_before_writing(tmp_path, monkeypatch):
    from warpsense.study import load_plan

    monkeypatch.setenv("PATH", "/nonexistent")
    out = tmp_path / "study"
    with pytest.raises(MPSError):
        runner.run_cells(load_plan("smoke"), out, gpus=["0", "1"], mps="on")
    assert not out.exists()
