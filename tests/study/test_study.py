"""`warpsense study` end to end on the CPU: the smoke plan's cameras, interrupted and resumed without retraining, a
failing cell reported and skipped, the report; bad plans refused before anything is written; the local pool."""

import json
import os
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.reliability.conftest import assert_clean_failure
from warpsense.cli import main
from warpsense.config import load_config, tomllib
from warpsense.resources import CONFIG_DIR
from warpsense.study import gpus as study_gpus
from warpsense.study import (
    load_plan,
    render_text,
    reuse,
    run_cells,
    runner,
    study_dir,
    study_record,
    training,
    work,
    worker,
)
from warpsense.study.plan import PlanError
from warpsense.study.report import precision_recall
from warpsense.study.run_times import run_seconds
from warpsense.train import engine

FAST = ["train.epochs=2", "data.scenes_train=16", "data.scenes_val=4", "train.eval_every=2"]
BROKEN = '''
[[camera]]
name = "broken"               # the fixed ISP cannot demosaic clear pixels: fails when the cell builds its model
set = ["cfa.mode=\\"fixed\\"", "cfa.pattern=\\"RCCB\\"", "isp.enabled=true"]
'''


def _plan_file(tmp_path: Path, extra: str = "") -> Path:
    """The shipped smoke plan with the ``extra`` TOML appended."""
    path = tmp_path / "plan.toml"
    path.write_text((CONFIG_DIR / "studies" / "smoke.toml").read_text() + extra)
    return path


def test_smoke_study_runs_resumes_skips_failures_and_reports(tmp_path, monkeypatch, capsys):
    plan = load_plan(_plan_file(tmp_path, BROKEN), FAST)
    out = tmp_path / "study"
    assert [cell.id for cell in plan.cells()][:4] == ["rggb/night/0", "rccb/night/0", "learned/night/0",
                                                       "broken/night/0"]
    # Ctrl-C in the second cell's first epoch, after its checkpoint was written
    write_epoch, writes = engine._write_epoch, []

    def interrupting(run_dir, *args, **kwargs):
        write_epoch(run_dir, *args, **kwargs)
        writes.append(run_dir.name)
        if run_dir.name == "rccb.night.seed0":
            raise KeyboardInterrupt

    monkeypatch.setattr(engine, "_write_epoch", interrupting)
    assert run_cells(plan, out) == 130
    assert writes == ["rggb.night.seed0", "rggb.night.seed0", "rccb.night.seed0"]
    assert "interrupted; run the same command again" in capsys.readouterr().err
    monkeypatch.setattr(engine, "_write_epoch", write_epoch)

    trained = []
    real_train = engine.train
    monkeypatch.setattr(engine, "train", lambda config, resume=False, **kw: trained.append(
        (config.run.name, bool(resume))) or real_train(config, resume=resume, **kw))
    assert run_cells(plan, out) == 1  # a cell failed; the others finished
    printed = capsys.readouterr()
    assert trained[0] == ("rccb.night.seed0", True)  # the interrupted cell resumed ...
    assert ("rggb.night.seed0", False) not in trained  # ... the finished one was never retrained
    assert "[1/8] rggb/night/0: finished earlier, skipped" in printed.out
    assert "broken/night/0: FAILED: ValueError: the fixed ISP needs an R/G/B layout" in printed.err
    assert "2 of 8 cells failed: broken/night/0, broken/night/1" in printed.err
    rccb = [json.loads(line) for line in (out / "runs" / "rccb.night.seed0" / "metrics.jsonl").read_text().splitlines()]
    assert [record["epoch"] for record in rccb] == [0, 1]  # epoch 1 was not redone

    trained.clear()
    assert run_cells(plan, out) == 1 and [name for name, _ in trained] == ["broken.night.seed0", "broken.night.seed1"]
    capsys.readouterr()
    # study status says which cells failed and why (a local run's failure was "pending, not started")
    assert main(["study", "status", str(out)]) == 0
    lines = [line.split(None, 2) for line in capsys.readouterr().out.splitlines() if "/night/" in line]
    states = {cell: (state, detail) for cell, state, detail in lines}
    failure = "ValueError: the fixed ISP needs an R/G/B layout, got [['R', 'C'], ['C', 'B']]; not started"
    assert states["broken/night/0"] == states["broken/night/1"] == ("failed", failure)
    assert [state for state, _ in states.values()] == ["done"] * 3 + ["failed"] + ["done"] * 3 + ["failed"]

    record = study_record(out, resamples=100)
    assert record["missing"] == ["broken/night/0", "broken/night/1"] and len(record["cells"]) == 6
    val = record["splits"]["val"]
    assert [group["camera"] for group in val["groups"]] == ["rggb", "rccb", "learned"]
    evaluations = {seed: json.loads((out / "runs" / f"rccb.night.seed{seed}" / "evaluation.json").read_text())
                   for seed in (0, 1)}
    rccb_group = val["groups"][1]
    # wall time: the interrupted process's and the resuming one's, each at its last epoch
    rccb_cells = [c for c in record["cells"] if c["camera"] == "rccb"]
    assert rccb_cells[0]["run_s"] == pytest.approx(rccb[0]["wall_s"] + rccb[1]["wall_s"])
    assert rccb_group["run_s"] == pytest.approx(np.mean([c["run_s"] for c in rccb_cells]))
    assert rccb_group["timed_runs"] == 2
    assert rccb_group["miou"]["mean"] == pytest.approx(
        sum(e["splits"]["val"]["miou"] for e in evaluations.values()) / 2)
    # per-class precision and recall: each seed's pixels summed over the split's images, then the mean over seeds
    counts = {seed: np.array(e["splits"]["val"]["image_counts"], dtype=np.float64).sum(0)
              for seed, e in evaluations.items()}
    for k, name in enumerate(evaluations[0]["class_names"]):
        for key, column in (("per_class_precision", 1), ("per_class_recall", 2)):
            seen = [c[k, 0] / (c[k, 0] + c[k, column]) for c in counts.values() if c[k, 0] + c[k, column] > 0]
            interval = rccb_group[key][name]
            assert (interval is None) if not seen else interval["mean"] == pytest.approx(np.mean(seen))
    comparison = val["comparisons"][0]
    assert comparison["camera"] == "rccb" and comparison["reference"] == "rggb"
    assert comparison["paired"]["seeds"] == [0, 1]
    assert comparison["verdict"] in ("better", "worse", "not distinguishable")
    reference = {seed: json.loads((out / "runs" / f"rggb.night.seed{seed}" / "evaluation.json").read_text())
                 for seed in (0, 1)}
    differences = [evaluations[s]["splits"]["val"]["miou"] - reference[s]["splits"]["val"]["miou"] for s in (0, 1)]
    higher, lower = sum(d > 0 for d in differences), sum(d < 0 for d in differences)
    assert (comparison["paired"]["higher"], comparison["paired"]["lower"]) == (higher, lower)
    text = render_text(record)  # the console text is rendered from the record
    side = f", higher on {higher} of 2 seeds" if higher >= lower else f", lower on {lower} of 2 seeds"
    assert f"{comparison['verdict']}{side}" in text
    assert f"{rccb_group['miou']['mean']:.4f}" in text and "missing: broken/night/0, broken/night/1" in text
    assert f"seeds 0,1  {rccb_group['run_s']:.0f} s/run" in text
    assert "[val] per class, % means over seeds: IoU (precision/recall)" in text and "night/rccb" in text
    assert record["cells"][0]["learned_camera"]["cfa_layout"] == "RGGB"

    json_out, plot_out = tmp_path / "report.json", tmp_path / "report.png"
    assert main(["study", "report", str(out), "--json", str(json_out), "--plot", str(plot_out),
                 "--resamples", "100"]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {json_out}\n" in printed and f"wrote {plot_out}\n" in printed
    assert json.loads(json_out.read_text())["splits"]["val"]["groups"] == json.loads(json.dumps(val["groups"]))
    assert plot_out.stat().st_size > 10_000


@pytest.mark.parametrize("name", sorted(p.stem for p in (CONFIG_DIR / "studies").glob("*.toml")))
def test_every_shipped_plan_resolves_each_cell(name, tmp_path):
    """load_plan resolves every cell's config (presets, overrides, light); the cells are distinct runs. A plan on a
    dataset that is not here (CamVid at ../shared/data) skips, naming the folder: its sequence folds are read from
    the dataset's split lists (it failed with PlanError 'CamVid split list not found' on a machine without them)."""
    base = tomllib.loads((CONFIG_DIR / "studies" / f"{name}.toml").read_text())["study"].get("base") or None
    data = load_config(base).data
    if data.dataset != "scenes" and not Path(data.root).is_dir():
        pytest.skip(f"plan {name}: its {data.dataset} data is not found at {Path(data.root).resolve()} (base "
                    f"{base}: data.root = {data.root!r})")
    plan = load_plan(name)
    cells = plan.cells()
    assert len({cell.run_name for cell in cells}) == len(cells) == len(plan.seeds) * len(plan.fold_names()) * sum(
        len(light.cameras or plan.cameras) for light in plan.lights)
    offsets = {camera.seed_offset for camera in plan.cameras}
    assert {plan.config(cell, tmp_path).run.seed for cell in cells} == {s + o for s in plan.seeds for o in offsets}
    folds = {(plan.config(cell, tmp_path).data.holdout_sequence, plan.config(cell, tmp_path).data.holdout_block)
             for cell in cells}
    assert folds == ({("", j) for j in range(1, plan.blocks + 1)} if plan.folds == "blocks" else
                     {(name, 0) for name in plan.sequences or [""]})


def test_plan_only_prints_one_command_per_cell(tmp_path, capsys):
    assert main(["study", "run", "smoke", "--out", str(tmp_path / "s"), "--plan-only", "--set", "train.epochs=3"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    # a comment line first (a shell skips it): the regime the cells are judged in
    assert lines[0] == "# no folds (the train split; judged on val): train 96 frames (92% of the labelled frames), " \
        "judge 8 frames"
    commands = lines[1:]
    assert len(commands) == 6 and not (tmp_path / "s").exists()
    words = shlex.split(commands[1])
    assert words[:3] == ["warpsense", "study", "run"] and words[-4:] == ["--cell", "rccb/night/0", "--set",
                                                                         "train.epochs=3"]
    # --reuse travels into each cell's command, so a scheduler copies in what the local run would (not retrain it)
    (tmp_path / "old" / "runs").mkdir(parents=True)
    assert main(["study", "run", "smoke", "--out", str(tmp_path / "s"), "--plan-only", "--reuse",
                 str(tmp_path / "old")]) == 0
    words = shlex.split(capsys.readouterr().out.strip().splitlines()[2])
    assert words[-4:] == ["--cell", "rccb/night/0", "--reuse", str(tmp_path / "old")]


def test_the_local_pool_gives_the_same_cells_as_one_process(tmp_path, capsys):
    plan = load_plan("smoke", FAST)
    cells = [cell for cell in plan.cells() if cell.camera == "rggb"]
    assert run_cells(plan, tmp_path / "here", cells) == 0
    assert run_cells(plan, tmp_path / "pool", cells, gpus=["0", "1"], per_gpu=1) == 0  # fake GPU ids, CPU cells
    assert "started on GPU 0" in capsys.readouterr().out
    for cell in cells:
        here, pool = (json.loads((tmp_path / where / "runs" / cell.run_name / "evaluation.json").read_text())
                      for where in ("here", "pool"))
        assert here["splits"] == pool["splits"]


def test_fewer_cells_than_slots_spread_over_the_gpus(tmp_path, capsys):
    """Two cells, two GPUs of two slots each: one cell a GPU (the first GPU's slots start first and took both)."""
    import re

    plan = load_plan("smoke", FAST)
    cells = plan.cells()[:2]
    assert run_cells(plan, tmp_path, cells, gpus=["0", "1"], per_gpu=2) == 0
    assert sorted(re.findall(r"started on GPU (\d)", capsys.readouterr().out)) == ["0", "1"]


FAKE_WORKER = """
import json, pathlib, sys, time
out = pathlib.Path(sys.argv[1])
for line in sys.stdin:  # the pool's protocol: a cell's fields a line, answered done once its evaluation is written
    cell = json.loads(line)
    assert isinstance(cell["seed"], int)
    name = ".".join([cell["camera"], cell["light"], *([cell["fold"]] if cell["fold"] else []), f"seed{cell['seed']}"])
    run = out / "runs" / name
    run.mkdir(parents=True, exist_ok=True)
    time.sleep(0.2)
    (run / "evaluation.json").write_text(json.dumps({"splits": {"val": {"miou": 0.5}}}))
    print(json.dumps({"cell": cell, "done": True, "reason": ""}), flush=True)
"""


def test_the_pool_hands_out_the_longest_cells_first_and_balances_each_gpus_work(tmp_path, capsys, monkeypatch):
    """Cells of three lengths (as CamVid's folds: 406, 367 and 163 training frames) x 4 seeds on 4 GPUs x 3 slots:
    each GPU runs one cell of each length. Handed out in plan order and balanced by count, one GPU of the answers
    study took the three longest (docs/benchmarks.md, studies per GPU-hour)."""
    import collections
    import re
    import sys

    plan = load_plan(_plan_file(tmp_path), FAST + ["study.seeds=[0,1,2,3]"])
    frames = {"rggb": 163, "rccb": 406, "learned": 367}  # the shortest first in plan order
    monkeypatch.setattr(work, "cell_work", lambda plan, cells: {cell: frames[cell.camera] for cell in cells})
    monkeypatch.setattr(worker, "worker_command",
                        lambda plan, out, progress=False: [sys.executable, "-c", FAKE_WORKER, str(out)])
    assert run_cells(plan, tmp_path / "study", gpus=["0", "1", "2", "3"], per_gpu=3) == 0
    printed = capsys.readouterr().out
    started = re.findall(r"\] (\w+)/night/\d: started on GPU (\d)", printed)
    assert len(started) == 12  # (the lines print outside the pool's lock: their order is not the hand-out's)
    by_gpu = collections.defaultdict(list)
    for camera, gpu in started:
        by_gpu[gpu].append(camera)
    assert {gpu: sorted(cameras) for gpu, cameras in by_gpu.items()} == {
        gpu: ["learned", "rccb", "rggb"] for gpu in "0123"}
    assert printed.count("done in") == 12


def test_cell_work_counts_epochs_frames_and_crop_pixels(tmp_path, monkeypatch):
    """A cell's work is epochs x training frames x crop pixels (independent counts: the smoke plan's 16 generated
    training scenes); a training set that cannot be read gives every cell the same work (plan order)."""
    plan = load_plan(_plan_file(tmp_path, '''
[[camera]]
name = "long"
set = ["data.max_train_images=10"]
'''), [*FAST, "train.epochs=3"])
    cells = plan.cells()
    lengths = work.cell_work(plan, cells)
    assert {cell.camera: lengths[cell] for cell in cells} == {"rggb": 3 * 16 * 48 * 64, "rccb": 3 * 16 * 48 * 64,
                                                           "learned": 3 * 16 * 48 * 64, "long": 3 * 10 * 48 * 64}
    plan = load_plan(_plan_file(tmp_path), [*FAST, "train.epochs=2", "data.crop_height=32"])  # crop pixels count
    assert set(work.cell_work(plan, plan.cells()).values()) == {2 * 16 * 32 * 64}

    def unreadable(data_config, seed=0):
        raise engine.DatasetError("train.txt: no such file")

    monkeypatch.setattr("warpsense.data.build_training", unreadable)
    assert set(work.cell_work(plan, cells).values()) == {1}


def test_a_failure_record_that_cannot_be_written_does_not_stop_the_study(tmp_path, monkeypatch):
    """The record for `study status` is best effort: with a full disk, writing it raised inside the pool's slot,
    whose thread died with the cells it had not taken yet."""
    plan = load_plan("smoke", FAST)

    def full_disk(target):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(study_dir, "atomic_write", full_disk)
    study_dir.record_failure(tmp_path, plan.cells()[0], "RuntimeError: boom")
    assert study_dir.recorded_failure(tmp_path, plan.cells()[0]) is None


def test_a_worker_that_cannot_start_fails_its_cells_and_the_pool_goes_on(tmp_path, capsys, monkeypatch):
    """Every worker fails to start (here: no such program): each cell is reported failed (none lost, exit 1) and no
    slot waits for a GPU whose slots stopped."""

    plan = load_plan("smoke", FAST)
    cells = plan.cells()[:5]
    monkeypatch.setattr(worker, "worker_command", lambda plan, out, progress=False: [str(tmp_path / "no-such-worker")])
    assert run_cells(plan, tmp_path / "study", cells, gpus=["0", "1"], per_gpu=2) == 1
    err = capsys.readouterr().err
    assert err.count(": FAILED (") == len(cells) and f"{len(cells)} of {len(cells)} cells failed" in err
    # each failure is recorded for `study status` until the cell trains again
    assert all("no-such-worker" in study_dir.recorded_failure(tmp_path / "study", cell) for cell in cells)
    import sys

    monkeypatch.setattr(worker, "worker_command",
                        lambda plan, out, progress=False: [sys.executable, "-c", FAKE_WORKER, str(out)])
    assert run_cells(plan, tmp_path / "study", cells, gpus=["0", "1"], per_gpu=2) == 0
    assert [study_dir.recorded_failure(tmp_path / "study", cell) for cell in cells] == [None] * len(cells)


def test_the_local_pool_trains_its_cells_on_one_worker_process_per_slot(tmp_path, capsys):
    """One GPU slot, three cells: one worker process trains them all (its pid in each cell's log), so that the
    interpreter, CUDA context and kernel modules are paid once per slot, not once per cell."""
    import re

    plan = load_plan("smoke", FAST)
    cells = plan.cells()[:3]
    assert run_cells(plan, tmp_path, cells, gpus=["0"], per_gpu=1) == 0
    pids = {re.search(r"in worker process (\d+)", (tmp_path / "logs" / f"{cell.run_name}.log").read_text()).group(1)
            for cell in cells}
    assert len(pids) == 1 and str(os.getpid()) not in pids
    assert all((tmp_path / "runs" / cell.run_name / "evaluation.json").is_file() for cell in cells)


def test_progress_reaches_the_pool_workers_as_bars_in_each_cells_log(tmp_path, capsys):
    """`study run --progress` with a pool: each worker draws its cell's progress bars into the cell's log (one
    terminal would interleave several workers' bars), and the command says where they are."""
    import re

    plan = load_plan("smoke", FAST)
    cell = plan.cells()[0]
    assert run_cells(plan, tmp_path, [cell], gpus=["0"], per_gpu=1, progress=True) == 0
    log = (tmp_path / "logs" / f"{cell.run_name}.log").read_text()
    assert re.search(r"epoch 1/2 \(\w+\): +\d+%\|", log)  # a tqdm bar of the first epoch
    assert "--progress: each cell's progress bars go to its log" in capsys.readouterr().out
    assert "--progress" not in worker.worker_command(plan, tmp_path)


def test_a_pool_worker_sees_its_gpu_and_its_share_of_the_cores():
    """Each worker gets one GPU and cores // workers OpenMP threads (two workers of 16 threads each on 16 cores made
    every cell's set-up 5-8x slower on the 2 x H100 machine); a thread count the caller set is kept."""
    from warpsense.study.worker import worker_environment

    environment = worker_environment("1", 2, {"PATH": "/bin", "CUDA_VISIBLE_DEVICES": "0,1"}, cores=16)
    assert environment == {"PATH": "/bin", "CUDA_VISIBLE_DEVICES": "1", "OMP_NUM_THREADS": "8"}
    assert worker_environment("0", 6, {}, cores=4)["OMP_NUM_THREADS"] == "1"
    assert worker_environment("0", 2, {"OMP_NUM_THREADS": "3"}, cores=16)["OMP_NUM_THREADS"] == "3"


def test_pool_ids_count_within_the_parents_cuda_visible_devices(monkeypatch):
    """A pool id is an index into this process's CUDA_VISIBLE_DEVICES, as torch's cuda:N: with 2,3 (a Slurm
    allocation) the workers of ids 0 and 1 get "2" and "3", not the machine's GPUs 0 and 1; UUIDs are passed on
    as they are; unset, the id itself. Under the pool's MPS daemon the id stays bare (the daemon renumbers)."""
    from warpsense.study.worker import worker_environment

    def device(gpu, extra=None):
        return worker_environment(gpu, 2, cores=4, extra=extra)["CUDA_VISIBLE_DEVICES"]

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,3")
    assert [device("0"), device("1")] == ["2", "3"]
    assert device("1", extra={"CUDA_MPS_PIPE_DIRECTORY": "/tmp/pipe"}) == "1"
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "GPU-aaa, GPU-bbb")
    assert [device("0"), device("1")] == ["GPU-aaa", "GPU-bbb"]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "MIG-0f1e2d3c-aaaa-bbbb-cccc-000000000001")
    assert device("0") == "MIG-0f1e2d3c-aaaa-bbbb-cccc-000000000001"
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    assert [device("0"), device("1")] == ["0", "1"]


@pytest.mark.parametrize("visible, shown", [("2,3", "CUDA_VISIBLE_DEVICES=2,3"), ("", "CUDA_VISIBLE_DEVICES=(empty")])
def test_a_pool_id_past_the_visible_devices_is_one_error_naming_gpus(monkeypatch, visible, shown):
    from warpsense.study.worker import worker_environment

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", visible)
    for extra in (None, {"CUDA_MPS_PIPE_DIRECTORY": "/tmp/pipe"}):
        with pytest.raises(ValueError) as error:
            worker_environment("2", 2, cores=4, extra=extra)
        message = str(error.value)
        assert message.startswith("--gpus 2: ") and shown in message and "\n" not in message


def test_the_gpu_reading_child_sees_the_workers_gpus(monkeypatch, uuid_cache):
    """cuda_uuids's child process gets the same devices as the workers (ids mapped through CUDA_VISIBLE_DEVICES),
    so the memory and busy readings are of the GPUs the pool really uses."""
    import subprocess

    seen = []

    def run(command, env=None, **kwargs):
        seen.append(env["CUDA_VISIBLE_DEVICES"])
        uuids = [f"{n:08x}-aaaa-bbbb-cccc-000000000000" for n in range(len(env["CUDA_VISIBLE_DEVICES"].split(",")))]
        return subprocess.CompletedProcess(command, 0, "\n".join(uuids) + "\n", "")

    monkeypatch.setattr(subprocess, "run", run)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,3")
    assert study_gpus.cuda_uuids(("1", "0")) is not None and seen == ["3,2"]
    assert study_gpus.cuda_uuids(("2",)) is None and seen == ["3,2"]  # past the visible devices: nothing to read


def test_explicit_gpu_ids_are_checked_against_the_visible_devices(monkeypatch):
    """--gpus ids past torch's device count are refused also where CUDA_VISIBLE_DEVICES is set (they count within
    it), in one line naming --gpus and the visible devices."""
    import torch

    from warpsense.study.launch import check_local_gpus

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,3")
    check_local_gpus(["0", "1"])
    with pytest.raises(ValueError) as error:
        check_local_gpus(["0", "2"])
    assert str(error.value) == ("--gpus 0,2: GPU 2 not found; CUDA_VISIBLE_DEVICES=2,3 makes 2 visible, counted "
                                "from 0 as in PyTorch (ids 0-1)")
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    with pytest.raises(ValueError, match=r"^--gpus 3: GPU 3 not found; this machine has 2 \(ids 0-1\)$"):
        check_local_gpus(["3"])


def test_report_split_without_plot_is_one_line_error(tmp_path, capsys):
    """`study report DIR --split heldout` without --plot was checked and then ignored (the text and --json hold every
    split; --split picks the one the plot draws): a one-line error naming both, before the study is read."""
    assert_clean_failure(capsys, ["study", "report", str(tmp_path / "no_such_study"), "--split", "heldout"],
                         ("--split heldout", "add --plot"), watched=tmp_path)


@pytest.mark.parametrize("gpus, per_gpu, pool", [("1", "1", ["1"]), ("0", "1", None), ("0", "2", ["0"]),
                                                   ("0,1", "1", ["0", "1"]), ("none", "1", None)])
def test_one_gpu_other_than_the_first_runs_on_a_worker_given_that_gpu(tmp_path, monkeypatch, gpus, per_gpu, pool):
    """`--gpus 1 --per-gpu 1` ran its cells in the command's process, whose training takes cuda:0 whatever --gpus
    says: the GPU the user kept free for someone else. Only the first visible GPU (or none) runs here; another
    single GPU gets a worker process whose CUDA_VISIBLE_DEVICES names it."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    given = []
    monkeypatch.setattr(runner, "run_cells", lambda plan, out, gpus=None, **kwargs: given.append(gpus) or 0)
    assert main(["study", "run", "smoke", "--out", str(tmp_path / "study"), "--gpus", gpus, "--per-gpu", per_gpu,
                 "--mps", "off"]) == 0
    assert given == [pool]


@pytest.mark.parametrize("gpus, pool", [("1", ["1"]), ("0", None), ("none", None), ("0,1", None), ("auto", None),
                                        ("2,1", ["2"]), ("1,0", None)])
def test_one_cell_on_a_gpu_named_alone_runs_there(tmp_path, monkeypatch, gpus, pool):
    """`--cell X --gpus 1` (or `--gpus 2,1`) trained in the command's process, on cuda:0 whatever --gpus said: where
    --gpus names GPUs but not the first, the first it names gets one worker process; otherwise the cell trains here."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 3)
    given = []
    monkeypatch.setattr(runner, "run_cells", lambda plan, out, cells, gpus=None, **kwargs: given.append(gpus) or 0)
    cell = load_plan("smoke", FAST).cells()[0].id
    assert main(["study", "run", "smoke", "--out", str(tmp_path / "study"), "--cell", cell, "--gpus", gpus]) == 0
    assert given == [pool]


@pytest.mark.parametrize("options, noted", [(["--per-gpu", "3"], True), (["--mps", "on"], True),
                                             (["--per-gpu", "auto"], False), (["--per-gpu", "1"], False)])
def test_gpu_options_without_a_gpu_say_what_they_do(tmp_path, monkeypatch, capsys, options, noted):
    """A GPU machine's command line (--per-gpu 3, --mps on) run without a pool of GPUs (--gpus none, or auto on a
    machine without CUDA) says in one line that the cells run one at a time in this process, instead of ignoring
    the options silently."""
    monkeypatch.setattr(runner, "run_cells", lambda plan, out, gpus=None, **kwargs: 0)
    assert main(["study", "run", "smoke", "--out", str(tmp_path / "study"), "--gpus", "none", *options]) == 0
    printed = capsys.readouterr().out
    assert ("study: no pool of GPUs (--gpus none): the cells run one at a time in this process" in printed) == noted


def test_a_worker_that_dies_fails_its_cell_and_a_fresh_one_takes_the_next(tmp_path, monkeypatch, capsys):
    """A worker process that exits without answering (a crash) fails the cell it held, with its exit status, and the
    slot starts a new worker for the next cell; the study reports both failures and exits 1."""
    import sys


    started = []

    def dying_worker(plan, out, progress=False):
        started.append(1)
        return [sys.executable, "-c", "import sys; sys.stdin.readline(); sys.exit(3)"]

    monkeypatch.setattr(worker, "worker_command", dying_worker)
    plan = load_plan("smoke", FAST)
    cells = plan.cells()[:2]
    assert run_cells(plan, tmp_path, cells, gpus=["0"], per_gpu=1) == 1
    err = capsys.readouterr().err
    assert err.count("FAILED (worker exit 3)") == 2 and len(started) == 2
    assert "2 of 2 cells failed" in err


def test_a_worker_answers_each_cell_and_goes_on_past_a_failed_one(tmp_path, monkeypatch, capfd):
    """The worker protocol: a cell's typed fields on stdin (a JSON object a line), one answer line each on stdout; a
    cell's output and a failure's traceback go to its log, and the next cell still trains. A line that is not a cell
    of the plan (a bare id, a seed as text, a cell of no such camera) is answered failed, naming it, and the worker
    goes on: the seed reaches the worker as the integer the plan made, never parsed back from text."""
    import dataclasses
    import io

    plan = load_plan("smoke", FAST)
    bad, good = plan.cells()[:2]
    real = training.train_cell

    def train_cell(plan, out, cell, progress=False):
        if cell == bad:
            raise ValueError("no light to see by\nsecond line")
        return real(plan, out, cell, progress)

    monkeypatch.setattr(training, "train_cell", train_cell)
    text_seed = json.dumps({**dataclasses.asdict(good), "seed": str(good.seed)})
    unknown = json.dumps({**dataclasses.asdict(good), "camera": "no_such_camera"})
    lines = [worker.cell_line(bad), good.id, text_seed, unknown, worker.cell_line(good)]
    monkeypatch.setattr("sys.stdin", io.StringIO("".join(line + "\n" for line in lines)))
    study_dir.record_plan(plan, tmp_path)
    (tmp_path / "logs").mkdir()
    assert worker.cell_worker(plan, tmp_path) == 0
    answers = [worker.Answer.parse(line) for line in capfd.readouterr().out.splitlines()]
    assert answers[0] == worker.Answer(bad, False, "ValueError: no light to see by")
    assert answers[4] == worker.Answer(good, True)
    for refused in answers[1:4]:
        assert refused.cell is None and not refused.done and refused.reason.startswith("PlanError: ")
    assert "not a cell of the pool's protocol" in answers[1].reason and repr(good.id) in answers[1].reason
    assert "not a cell of the pool's protocol" in answers[2].reason  # the seed as text is not taken for a number
    assert "no cell 'no_such_camera/" in answers[3].reason
    assert "Traceback" in (tmp_path / "logs" / f"{bad.run_name}.log").read_text()
    assert study_dir.cell_state(tmp_path, bad) == "new" and study_dir.cell_state(tmp_path, good) == "done"
    assert "epoch" in (tmp_path / "logs" / f"{good.run_name}.log").read_text()


def test_the_pool_fails_a_cell_whose_worker_answers_for_another_or_not_at_all(tmp_path, capsys, monkeypatch):
    """A worker's line that is no answer (stray output on stdout) or answers another cell fails the cell it was
    given, saying so; nothing is taken as done without its own answer."""
    import sys

    script = """
import json, sys
for number, line in enumerate(sys.stdin):
    cell = json.loads(line)
    if number == 0:
        print("progress 50%", flush=True)
    else:
        print(json.dumps({"cell": {**cell, "seed": cell["seed"] + 1}, "done": True, "reason": ""}), flush=True)
"""
    monkeypatch.setattr(worker, "worker_command", lambda plan, out, progress=False: [sys.executable, "-c", script])
    plan = load_plan("smoke", FAST)
    cells = plan.cells()[:2]
    assert run_cells(plan, tmp_path, cells, gpus=["0"], per_gpu=1) == 1
    err = capsys.readouterr().err
    assert "FAILED (the worker's answer is not one: 'progress 50%')" in err
    assert "FAILED (the worker answered for another cell (done))" in err and "2 of 2 cells failed" in err


def test_reuse_copies_in_another_studys_runs_of_the_same_training_and_trains_the_rest(tmp_path, capsys):
    """`--reuse DIR`: a cell whose resolved config another study's finished run trained (all but run.name and
    run.output_dir equal) is copied in, not trained; a cell that differs in anything else is trained."""
    earlier = load_plan("smoke", FAST)
    cell = earlier.cells()[0]
    assert run_cells(earlier, tmp_path / "earlier", [cell]) == 0
    capsys.readouterr()
    later = tmp_path / "later.toml"  # the same cameras under another study name
    later.write_text((CONFIG_DIR / "studies" / "smoke.toml").read_text().replace('name = "smoke"', 'name = "later"'))
    out = tmp_path / "later"
    assert main(["study", "run", str(later), "--out", str(out), "--gpus", "none", "--cell", cell.id,
                 "--reuse", str(tmp_path / "earlier"), *sum((["--set", text] for text in FAST), [])]) == 0
    source = tmp_path / "earlier" / "runs" / cell.run_name
    assert f"{cell.id}: the same training as {source}, copied in" in capsys.readouterr().out
    assert (out / "runs" / cell.run_name / "evaluation.json").read_text() == (source / "evaluation.json").read_text()
    assert not (out / "logs").exists() and not list((out / "runs").glob("*.reusing"))

    other = load_plan(later, FAST + ["train.lr=0.002"])  # the same cell at another learning rate: trained here
    assert run_cells(other, tmp_path / "other", [other.cell(cell.id)], reuse=[tmp_path / "earlier"]) == 0
    assert "copied in" not in capsys.readouterr().out
    config = json.loads((tmp_path / "other" / "runs" / cell.run_name / "config.json").read_text())
    assert config["train"]["lr"] == 0.002 and config["run"]["output_dir"] == str(tmp_path / "other" / "runs")
    assert_clean_failure(capsys, ["study", "run", "smoke", "--out", str(tmp_path / "x"), "--reuse",
                                  str(tmp_path / "nowhere")], ("--reuse", "nowhere", "runs/"))
    assert not (tmp_path / "x").exists()


def test_reuse_reads_an_older_runs_config_with_the_defaults_of_keys_added_since(tmp_path, capsys):
    """A run saved before a key existed (its config.json without model.full_depth) trained with that key's default,
    so it is reused for a cell at the default and not for one that sets the key; so is a run saved with a key since
    retired at the value of the behaviour that stayed (loss.lovasz_stride = 1). A run whose config has a key this
    version does not know, or asks for a retired behaviour, is passed over with its reason."""
    earlier = load_plan("smoke", FAST)
    cell = earlier.cells()[0]
    assert run_cells(earlier, tmp_path / "earlier", [cell]) == 0
    saved = tmp_path / "earlier" / "runs" / cell.run_name / "config.json"
    config = json.loads(saved.read_text())
    del config["model"]["full_depth"]
    config["loss"]["lovasz_stride"] = 1
    saved.write_text(json.dumps(config))
    passed_over = {}
    for name, section, key in (("unknown", "model", "gone"), ("retired", "loss", "lovasz_stride")):
        passed_over[name] = tmp_path / "earlier" / "runs" / name
        shutil.copytree(saved.parent, passed_over[name])
        (passed_over[name] / "config.json").write_text(json.dumps({**config, section: {**config[section], key: 2}}))
    capsys.readouterr()

    found = reuse.finished_runs([tmp_path / "earlier"])
    assert list(found.values()) == [saved.parent]
    printed = capsys.readouterr().out
    assert f"--reuse: {passed_over['unknown']} not considered: " in printed
    assert f"--reuse: {passed_over['retired']} not considered: loss.lovasz_stride = 2 was retired" in printed
    assert reuse.reuse_cells(earlier, tmp_path / "same", [cell], found) == {cell: saved.parent}
    deeper = load_plan("smoke", FAST + ["model.full_depth=2"])
    assert reuse.reuse_cells(deeper, tmp_path / "other", [deeper.cell(cell.id)], found) == {}


BAD_PLANS = [
    ("[study]\nseeds = [0]\nreference = \"a\"\ncolour = 1\n[[camera]]\nname = \"a\"\n[[light]]\nname = \"l\"\n"
     "full_well_electrons = 10.0\nread_electrons = 1.0\n", ("study.colour", "unknown key")),
    ("[study]\nseeds = [0]\nreference = \"a\"\n[[camera]]\nname = \"a\"\npreset = \"no_such_preset\"\n[[light]]\n"
     "name = \"l\"\nfull_well_electrons = 10.0\nread_electrons = 1.0\n", ("camera 'a'", "no_such_preset")),
    ("[study]\nseeds = [0]\nreference = \"b\"\n[[camera]]\nname = \"a\"\n[[light]]\nname = \"l\"\n"
     "full_well_electrons = 10.0\nread_electrons = 1.0\n", ("study.reference", "'b'")),
    ("[study]\nseeds = [0]\nreference = \"a\"\n[[camera]]\nname = \"a\"\n[[camera]]\nname = \"a\"\n[[light]]\n"
     "name = \"l\"\nfull_well_electrons = 10.0\nread_electrons = 1.0\n", ("camera.name", "duplicate")),
    ("[study]\nseeds = [0]\nreference = \"a\"\n[[camera]]\nname = \"a\"\nset = [\"cfa.pattern=XXXX\"]\n[[light]]\n"
     "name = \"l\"\nfull_well_electrons = 10.0\nread_electrons = 1.0\n", ("camera 'a'", "cfa.pattern")),
    ("[study]\nseeds = [0]\nreference = \"a\"\nset = [\"data.dataset=camvid\", \"data.root=/no/such/folder\"]\n"
     "[[camera]]\nname = \"a\"\n[[light]]\nname = \"l\"\nfull_well_electrons = 10.0\nread_electrons = 1.0\n",
     ("data:", "/no/such/folder")),
    ("[study]\nseeds = [0, 0]\nreference = \"a\"\n[[camera]]\nname = \"a\"\n[[light]]\nname = \"l\"\n"
     "full_well_electrons = 10.0\nread_electrons = 1.0\n", ("study.seeds",)),
    ("[study]\nseeds = [0]\nreference = \"a\"\n[[camera]]\nname = \"a\"\n[[light]]\nname = \"l\"\n"
     "full_well_electrons = 10.0\n", ("light[0]", "read_electrons")),
    ("[study]\nseeds = [0]\nreference = \"a\"\n[[camera]]\nname = \"a\"\n[[light]]\nname = \"l\"\n"
     "scene = \"noon\"\n", ("light[0].scene", "'noon'", "night")),
    ("[study]\nseeds = [0]\nreference = \"a\"\n[[camera]]\nname = \"a\"\n[[light]]\nname = \"l\"\n"
     "scene = \"day\"\n", ("camera 'a' at light 'l'", "photons.enabled")),
    ("[study]\nseeds = [0]\nreference = \"a\"\nbase = \"camvid_photons\"\n"
     "set = [\"data.dataset=scenes\"]\n[[camera]]\nname = \"a\"\n[[light]]\nname = \"l\"\n"
     "full_well_electrons = 10.0\nread_electrons = 1.0\n", ("camera 'a' at light 'l'", "scene")),
    ("[study]\nseeds = [0]\nreference = \"a\"\n[[camera]]\nname = \"a\"\n[[light]]\nname = \"l\"\n"
     "full_well_electrons = 10.0\nread_electrons = 1.0\nanalog_gain = 2.0\n", ("light[0].analog_gain",)),
    ("[study]\nseeds = [0]\nreference = \"a\"\n[[camera]]\nname = \"a\"\n", ("light",)),
    ("[study\n", ("invalid TOML",)),
]


@pytest.mark.parametrize("text, names", BAD_PLANS, ids=[f"bad{i}" for i in range(len(BAD_PLANS))])
def test_bad_plans_are_one_line_errors_before_any_output(text, names, tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert_clean_failure(capsys, ["study", "run", str(path), "--out", str(tmp_path / "out")], (str(path), *names),
                         watched=tmp_path)


def test_scene_lights_set_the_photon_budget_and_the_operating_point():
    from warpsense.study.plan import Cell, load_plan

    plan = load_plan("camvid_design", ["data.dataset=scenes"])
    night = plan.config(Cell("learned_design", "night", 0), "runs")
    day = plan.config(Cell("learned_design", "day", 1), "runs")
    assert (night.photons.light, night.photons.analog_gain, night.optics.exposure_ms) == ("night", 8.0, 10.0)
    assert (day.photons.light, day.photons.analog_gain, day.optics.exposure_ms) == ("day", 2.0, 2.5)
    assert day.run.seed == 1 and day.optics.f_number_learnable and day.cfa.candidates == "RGBCY"
    assert {cell.camera for cell in plan.cells() if cell.light == "day"} == {
        "fixed_isp", "raw_rggb", "raw_rccb", "raw_ryyb", "learned_design"}
    from warpsense.study.plan import Plan

    assert Plan.from_dict(json.loads(json.dumps(plan.to_dict()))) == plan  # as the report reads plan.json


def test_precision_recall_from_per_image_counts():
    """Counts [N, K, 3] = (TP, FP, FN) per image and class: pixels are summed over images first; a class never
    predicted has no precision, a class absent has no recall."""
    counts = [[[3, 1, 0], [0, 0, 2], [0, 4, 0]],
              [[1, 1, 4], [0, 0, 1], [0, 0, 0]]]
    precision, recall = precision_recall(counts)
    assert precision == [pytest.approx(4 / 6), None, 0.0]
    assert recall == [pytest.approx(4 / 8), 0.0, None]


def test_run_seconds_adds_the_processes_of_a_resumed_run(tmp_path):
    metrics = tmp_path / "metrics.jsonl"
    assert run_seconds(metrics) is None  # no log
    records = [{"epoch": 0, "setup_s": 2.0, "wall_s": 10.0}, {"epoch": 1, "wall_s": 20.0},  # process 1, then a kill
               {"epoch": 2, "setup_s": 1.0, "wall_s": 5.0}, {"epoch": 3, "wall_s": 9.0}]  # process 2 resumes
    metrics.write_text("".join(json.dumps(r) + "\n" for r in records) + "\n")
    assert run_seconds(metrics) == 29.0
    metrics.write_text(json.dumps({"epoch": 0, "setup_s": 1.0}) + "\n")  # a log from before wall_s was recorded
    assert run_seconds(metrics) is None


def test_report_names_the_learned_design():
    from warpsense.study.report import _learned

    camera = {"cfa_layout": "CCCC", "f_number": 1.9263, "exposure_ms": 11.21, "analog_gain": 7.991}
    assert _learned(camera) == "CFA CCCC; f/1.93; exposure 11.2 ms; analog gain 7.99"


def test_bad_study_directories_and_overrides(tmp_path, capsys):
    assert_clean_failure(capsys, ["study", "run", "smoke", "--out", str(tmp_path / "o"), "--set", "train.nope=1"],
                         ("train.nope",), watched=tmp_path)
    assert_clean_failure(capsys, ["study", "run", "no_such_plan", "--out", str(tmp_path / "o")],
                         ("no_such_plan", "smoke"), watched=tmp_path)
    assert_clean_failure(capsys, ["study", "report", str(tmp_path)], ("not a study directory",), watched=tmp_path)
    assert_clean_failure(capsys, ["study", "report", str(tmp_path / "missing")], ("no such study directory",))
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "plan.json").write_text(json.dumps(load_plan("smoke").to_dict()))
    assert_clean_failure(capsys, ["study", "report", str(tmp_path / "s")], ("no finished cell yet",),
                         watched=tmp_path)
    assert_clean_failure(capsys, ["study", "run", "smoke", "--out", str(tmp_path / "s"), "--set", "train.epochs=3"],
                         ("holds another plan",), watched=tmp_path)
    with pytest.raises(PlanError, match="no cell 'rggb/day/0'"):
        load_plan("smoke").cell("rggb/day/0")


def test_unreadable_study_records_are_one_line_errors_naming_the_file(tmp_path, capsys):
    """A torn or hand-edited plan.json, throughput.json or slurm/jobs.json: `study run` and `study status` printed
    json's message alone ("Expecting value: line 1 column 1 (char 0)", no file named), a plan.json of the wrong shape
    a bare key ("name"), and a run whose cells had all trained failed at its end the same way (now a warning there:
    the run's throughput entry is lost, not the study)."""
    out = tmp_path / "study"
    plan = load_plan("smoke", FAST)
    cell = plan.cells()[0]
    assert run_cells(plan, out, [cell], record=False) == 0
    run = ["study", "run", "smoke", "--out", str(out), "--gpus", "none", *(p for t in FAST for p in ("--set", t))]
    saved = (out / "plan.json").read_text()
    for text in ('{"name": "smo', "{}"):
        (out / "plan.json").write_text(text)
        for command in (run, ["study", "status", str(out)], ["study", "report", str(out), "--resamples", "20"]):
            assert_clean_failure(capsys, command, (str(out / "plan.json"),), watched=out)
    (out / "plan.json").write_text(saved)
    (out / "throughput.json").write_text("[{")
    assert_clean_failure(capsys, ["study", "report", str(out), "--resamples", "20"], (str(out / "throughput.json"),))
    capsys.readouterr()
    # at a run's end, when its cells have trained: a warning naming the file, the study does not fail there
    assert study_dir.record_throughput(out, 1, 1.0, None, 1, None)["cells_finished"] == 1
    assert f"study: warning: {out / 'throughput.json'}: unreadable" in capsys.readouterr().err
    assert (out / "throughput.json").read_text() == "[{"  # kept as it was, for its owner to mend
    (out / "slurm").mkdir()
    (out / "slurm" / "jobs.json").write_text("")
    assert_clean_failure(capsys, ["study", "status", str(out)], (str(out / "slurm" / "jobs.json"),))


def test_ctrl_c_stops_the_local_pool_and_a_rerun_resumes(tmp_path, capsys, ctrl_c):
    import os
    import signal
    import threading
    import time

    plan = load_plan("smoke", ["train.epochs=6", "data.scenes_train=16", "data.scenes_val=4", "train.eval_every=6"])
    cells = [cell for cell in plan.cells() if cell.camera == "rggb"]
    out = tmp_path / "pool"
    checkpoint = out / "runs" / cells[0].run_name / "checkpoint_last.safetensors"

    def interrupt_when_training():
        deadline = time.time() + 120
        while not checkpoint.exists() and time.time() < deadline:
            time.sleep(0.02)
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while the cells train (the main thread waits in the pool)

    watcher = threading.Thread(target=interrupt_when_training, daemon=True)
    watcher.start()
    assert run_cells(plan, out, cells, gpus=["0"], per_gpu=2) == 130
    watcher.join()
    assert "study: interrupted; run the same command again" in capsys.readouterr().err
    assert not (out / "runs" / cells[0].run_name / "evaluation.json").exists()
    assert run_cells(plan, out, cells, gpus=["0"], per_gpu=2) == 0
    log = (out / "logs" / f"{cells[0].run_name}.log").read_text()
    assert "resuming" in log  # the interrupted cell continued from its checkpoint
    for cell in cells:
        metrics = out / "runs" / cell.run_name / "metrics.jsonl"
        records = [json.loads(line) for line in metrics.read_text().splitlines()]
        assert [record["epoch"] for record in records] == list(range(6))


def test_throughput_is_recorded_with_the_sampled_gpu_busy_fraction(tmp_path, monkeypatch, capsys):
    """Each invocation appends cells finished, seconds and cells/hour; with a pool, the GPUs' busy fraction is the
    mean of nvidia-smi samples (here a fake nvidia-smi: GPU 0 at 80%, GPU 1 at 40%)."""

    monkeypatch.setattr(study_gpus, "gpu_busy", lambda gpus: [80.0, 40.0][: len(gpus)])
    plan = load_plan("smoke", FAST)
    cells = [cell for cell in plan.cells() if cell.camera == "rggb"]
    assert run_cells(plan, tmp_path, cells, gpus=["0", "1"], per_gpu=1) == 0
    assert run_cells(plan, tmp_path, cells) == 0  # nothing left to run: no entry
    entries = json.loads((tmp_path / study_dir.StudyDir.THROUGHPUT).read_text())
    assert len(entries) == 1
    entry = entries[0]
    assert entry["cells_finished"] == len(cells) and entry["gpus"] == ["0", "1"] and entry["per_gpu"] == 1
    assert entry["cells_per_hour"] == pytest.approx(len(cells) * 3600 / entry["seconds"])
    assert entry["gpu_busy_fraction"] == pytest.approx([0.8, 0.4])
    assert "cells/hour; GPU busy 80%, 40%" in capsys.readouterr().out
    from warpsense.study.report import render_text, study_record

    record = study_record(tmp_path)
    assert record["throughput"] == entries
    assert "2 GPU(s) x 1" in render_text(record) and "GPU busy 80%, 40%" in render_text(record)


SMI_ROWS = [  # nvidia-smi's rows, in its (PCI bus) order: UUID, free MiB, busy %
    ("GPU-11111111-aaaa-bbbb-cccc-000000000001", 81000.0, 5.0),
    ("GPU-22222222-aaaa-bbbb-cccc-000000000002", 20480.0, 97.0),
]


def _fake_gpus(rows=SMI_ROWS, cuda_order=(1, 0), lookup_works=True, calls=None):
    """A fake subprocess.run for nvidia-smi over ``rows`` and for the UUID lookup's child process, in which CUDA's
    device i (as CUDA_VISIBLE_DEVICES counts, FASTEST_FIRST by default) is nvidia-smi's row ``cuda_order[i]``."""
    import subprocess

    def run(command, env=None, **kwargs):
        if command[0] == "nvidia-smi":
            columns = {"index": lambda i: str(i), "uuid": lambda i: rows[i][0],
                       "memory.free": lambda i: str(rows[i][1]), "utilization.gpu": lambda i: str(rows[i][2])}
            fields = command[1].split("=", 1)[1].split(",")
            stdout = "".join(", ".join(columns[f](i) for f in fields) + "\n" for i in range(len(rows)))
        else:  # python -c: the UUIDs of the devices CUDA_VISIBLE_DEVICES names, as torch prints them
            (calls if calls is not None else []).append((command, env["CUDA_VISIBLE_DEVICES"]))
            if not lookup_works:
                raise subprocess.CalledProcessError(1, command)
            ids = [int(gpu) for gpu in env["CUDA_VISIBLE_DEVICES"].split(",")]
            visible = [cuda_order[i] for i in ids[:next((n for n, i in enumerate(ids) if i >= len(rows)), None)]]
            stdout = "".join(rows[i][0].removeprefix("GPU-") + "\n" for i in visible)
        return subprocess.CompletedProcess(command, 0, stdout, "")

    return run


@pytest.fixture
def uuid_cache():
    study_gpus.cuda_uuids.cache_clear()
    yield
    study_gpus.cuda_uuids.cache_clear()


def test_gpu_readings_are_the_cuda_ids_gpus_not_nvidia_smis_rows_of_the_same_number(monkeypatch, uuid_cache):
    """The pool's ids are CUDA's; nvidia-smi numbers its rows in PCI bus order, which CUDA's default order
    (FASTEST_FIRST) need not follow: each id's reading is the row of its GPU's UUID, looked up once in a child
    process (no CUDA context in the study's own process)."""
    import subprocess
    import sys

    calls = []
    monkeypatch.setattr(subprocess, "run", _fake_gpus(calls=calls))
    assert study_gpus.gpu_memory_gib(["0", "1"]) == [20.0, pytest.approx(81000 / 1024)]
    assert study_gpus.gpu_busy(["1", "0"]) == [5.0, 97.0]
    assert study_gpus.gpu_busy(["0", "1"]) == [97.0, 5.0]
    # one lookup per set of ids (cached: the busy sampler reads every 2 s), by this interpreter's torch
    assert [visible for _, visible in calls] == ["0,1", "1,0"]
    assert calls[0][0][:2] == [sys.executable, "-c"] and "uuid" in calls[0][0][2]
    monkeypatch.setattr(subprocess, "run", _fake_gpus(cuda_order=(0, 1)))  # CUDA_DEVICE_ORDER=PCI_BUS_ID
    study_gpus.cuda_uuids.cache_clear()
    assert study_gpus.gpu_busy(["0", "1"]) == [5.0, 97.0]
    assert study_gpus.gpu_busy(["2"]) is None  # no such GPU


def test_gpu_readings_unknown_where_the_ids_cannot_be_matched(monkeypatch, uuid_cache):
    """Without the UUIDs (no torch with CUDA in a child, an old torch) a reading of several GPUs is None, which
    --per-gpu auto takes as unknown (one cell a GPU); one GPU is CUDA's 0 whatever the order; no nvidia-smi, None."""
    import subprocess

    monkeypatch.setattr(subprocess, "run", _fake_gpus(lookup_works=False))
    assert study_gpus.gpu_memory_gib(["0", "1"]) is None and study_gpus.gpu_busy(["0"]) is None
    monkeypatch.setattr(subprocess, "run", _fake_gpus(rows=SMI_ROWS[1:], cuda_order=(0,), lookup_works=False))
    assert study_gpus.gpu_memory_gib(["0"]) == [20.0] and study_gpus.gpu_busy(["1"]) is None

    def missing(*args, **kwargs):
        raise FileNotFoundError("nvidia-smi")

    monkeypatch.setattr(subprocess, "run", missing)
    assert study_gpus.gpu_busy(["0"]) is None


def test_a_failed_cell_with_a_resume_point_says_how_to_start_it_again(tmp_path, monkeypatch, capsys):
    """A cell that fails while resuming (e.g. a corrupt checkpoint_last) would fail the same way on every retry: the
    summary names its run folder and says to delete it to train the cell from the start."""
    from warpsense.train.run_dir import LAST

    plan = load_plan("smoke", FAST)
    cell = plan.cells()[0]
    folder = study_dir.run_dir(tmp_path, cell)
    folder.mkdir(parents=True)
    (folder / LAST).write_bytes(b"not a checkpoint")

    def corrupt(*args, **kwargs):
        raise ValueError(f"{folder / LAST}: not a readable safetensors checkpoint")

    monkeypatch.setattr(training, "train_cell", corrupt)
    assert run_cells(plan, tmp_path, [cell]) == 1
    err = capsys.readouterr().err
    assert f"A retry resumes {folder} from its last checkpoint" in err and "delete that folder" in err
