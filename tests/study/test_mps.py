"""The study pool's CUDA MPS daemon, against a stand-in `nvidia-cuda-mps-control` that records how it was called."""

import os
import stat
from pathlib import Path

import pytest

from warpsense.study import gpus, mps, runner, work, worker
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
        variables = worker.worker_environment("1", 2, environ={}, cores=8, extra=environment)
        assert variables["CUDA_MPS_PIPE_DIRECTORY"] == str(pipe) and variables["CUDA_VISIBLE_DEVICES"] == "1"
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


def test_per_gpu_auto_takes_three_cells_a_gpu_under_mps_where_memory_holds_them(fake_control, monkeypatch):
    from warpsense.study.mps import AUTO_CELLS, RECIPE_PIXELS, auto_cells_per_gpu, cell_memory_gib

    h100 = [79.6] * 4
    assert auto_cells_per_gpu("auto", h100, RECIPE_PIXELS)[0] == AUTO_CELLS == 3
    small = [2.2 * cell_memory_gib(RECIPE_PIXELS)]  # two cells, but not with 10% to spare
    count, why = auto_cells_per_gpu("auto", small, RECIPE_PIXELS)
    assert count == 1 and "one fits" in why
    assert auto_cells_per_gpu("auto", [2.3 * cell_memory_gib(RECIPE_PIXELS)], RECIPE_PIXELS)[0] == 2
    assert auto_cells_per_gpu("auto", [*h100, 1.0], RECIPE_PIXELS)[0] == 1  # the smallest GPU decides
    assert auto_cells_per_gpu("auto", h100, 4 * RECIPE_PIXELS)[0] == 1  # four times the pixels a step: one fits
    count, why = auto_cells_per_gpu("off", h100, RECIPE_PIXELS)
    assert count == 1 and "time-sliced" in why
    assert auto_cells_per_gpu("auto", None, RECIPE_PIXELS) == (1, "the GPUs' memory could not be read (nvidia-smi)")
    monkeypatch.setenv("PATH", "/nonexistent")  # no MPS on this machine
    assert auto_cells_per_gpu("auto", h100, RECIPE_PIXELS)[0] == 1


def test_study_run_says_what_per_gpu_auto_chose(fake_control, monkeypatch, capsys):
    from warpsense.study import load_plan
    from warpsense.study.launch import pool_cells_per_gpu
    from warpsense.study.mps import RECIPE_PIXELS

    seen, measure = {}, work.step_pixels

    def pixels(plan):
        seen["pixels"] = measure(plan)
        return RECIPE_PIXELS

    monkeypatch.setattr(gpus, "gpu_memory_gib", lambda gpus: [79.6] * len(gpus))
    monkeypatch.setattr(work, "step_pixels", pixels)
    assert pool_cells_per_gpu(load_plan("smoke"), ["0", "1"], "auto") == 3
    assert "3 cell(s) at once on each GPU (--per-gpu auto: CUDA MPS, 80 GiB free a GPU" in capsys.readouterr().out
    config = load_plan("smoke").config(load_plan("smoke").cells()[0], "runs")
    assert seen["pixels"] == config.data.batch_size * config.data.crop_height * config.data.crop_width
    assert pool_cells_per_gpu(load_plan("smoke"), [], "auto") == 1  # no pool: nothing to choose


def test_study_run_passes_its_auto_choice_to_the_pool_and_falls_back_when_mps_fails(tmp_path, monkeypatch, capsys):
    """`--per-gpu auto`: one GPU at 1 runs in this process, at 3 a pool of three slots; an MPS daemon that cannot
    start turns the choice into one cell a GPU without MPS (an explicit --per-gpu keeps the error)."""
    from warpsense.study import launch as study

    calls = []

    def run_cells(plan, out, cells=None, gpus=None, per_gpu=1, mps="auto", **kwargs):
        calls.append((gpus, per_gpu, mps))
        if per_gpu > 1 and fail:
            raise MPSError("nvidia-cuda-mps-control -d exited 1: cannot start")
        return 0

    monkeypatch.setattr(study, "parse_gpus", lambda text: ["0"])
    monkeypatch.setattr(study, "check_local_gpus", lambda ids: None)
    monkeypatch.setattr(runner, "run_cells", run_cells)
    fail = False
    for chosen, expected in ((1, (None, 1, "auto")), (3, (["0"], 3, "auto"))):
        monkeypatch.setattr(study, "pool_cells_per_gpu", lambda plan, devices, mps, chosen=chosen: chosen)
        assert study.run_study("smoke", str(tmp_path / f"out{chosen}"), []) == 0
        assert calls.pop() == expected
    fail = True
    assert study.run_study("smoke", str(tmp_path / "fallback"), []) == 0
    assert calls == [(["0"], 3, "auto"), (None, 1, "off")]
    assert "cannot start; one cell at once on each GPU instead" in capsys.readouterr().err
    with pytest.raises(MPSError):
        study.run_study("smoke", str(tmp_path / "explicit"), [], per_gpu=3)
