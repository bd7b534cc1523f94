"""What `warpsense study run | status | report` do once their arguments are parsed: which path a study run takes
(one of the local pool's worker processes, the plan's commands for a scheduler of your own, one cell here, the
Slurm executor, or the local pool over this machine's GPUs; a plan with study.sequential or a [[search]] round after
round on the same runner), the GPUs a local pool may take, each cell's state, and the report's text, JSON and plots.
Every option is checked before anything is written; a wrong one is a ValueError naming it (the CLI's exit 2)."""

from __future__ import annotations

import sys
from pathlib import Path

from warpsense.files import check_output_file, check_output_folder, check_plot_file, write_json


def parse_gpus(text: str) -> list[str]:
    """``--gpus``: "auto" (every GPU torch sees, none without CUDA), "none", or ids "0,1,3"."""
    if text == "none":
        return []
    if text == "auto":
        import torch

        return [str(i) for i in range(torch.cuda.device_count())] if torch.cuda.is_available() else []
    ids = [part.strip() for part in text.split(",") if part.strip()]
    if not ids or not all(part.isdigit() for part in ids):
        raise ValueError(f"--gpus must be auto, none or GPU ids like 0,1; got {text!r}")
    return ids


def check_local_gpus(ids: list[str]) -> None:
    """GPU ids a local pool will give its workers must name GPUs this process sees: none without CUDA, and below
    torch's device count, which counts within this process's CUDA_VISIBLE_DEVICES (the ids do too, as torch's
    ``cuda:N``; the workers get the entries they name: `warpsense.study.gpus.cuda_device`)."""
    if not ids:
        return
    import torch

    from warpsense.study.gpus import visible_devices

    if not torch.cuda.is_available():
        raise ValueError(f"--gpus {','.join(ids)}: no CUDA device is visible here; use --gpus none (one process on "
                         "this machine's device) or auto")
    count = torch.cuda.device_count()
    missing = [gpu for gpu in ids if int(gpu) >= count]
    if missing:
        visible = visible_devices()
        seen = (f"this machine has {count}" if visible is None else
                f"CUDA_VISIBLE_DEVICES={','.join(visible)} makes {count} visible, counted from 0 as in PyTorch")
        raise ValueError(f"--gpus {','.join(ids)}: GPU {', '.join(missing)} not found; {seen} (ids 0-{count - 1})")
def run_study(plan_name: str, out: str, overrides: list[str], cell: str | None = None, plan_only: bool = False,
              gpus: str = "auto", per_gpu: int | str = "auto", progress: bool = False, worker: bool = False,
              reuse: list[str] | None = None, executor: str = "local", slurm: dict | None = None,
              mps: str = "auto", patterns: list[str] | None = None) -> int:
    """The `warpsense study run` command; returns the exit code. ``worker``: be one of the local pool's worker
    processes (`warpsense.study.worker.cell_worker`, cells on stdin). ``executor`` "slurm": submit the cells to
    Slurm (`warpsense.study.slurm.submit_study`) with ``slurm``, the keyword arguments of
    `warpsense.study.slurm.slurm_options` (None: not given). ``patterns``: shell patterns of the cell ids to run
    (`warpsense.study.plan.Plan.select`; none: every cell)."""
    from warpsense.study.command_lines import plan_commands
    from warpsense.study.folds import fold_lines, fold_sizes
    from warpsense.study.mps import check_mode as check_mps_mode
    from warpsense.study.plan import load_plan
    from warpsense.study.reuse import check_reuse_dirs
    from warpsense.study.runner import run_cells
    from warpsense.study.slurm import check_not_queued, slurm_options, submit_study
    from warpsense.study.study_dir import StudyDir
    from warpsense.study.training import check_runnable
    from warpsense.study.worker import cell_worker

    # every option is checked here, whichever path follows (worker, plan-only, one cell, pool, Slurm)
    if per_gpu != "auto" and (not isinstance(per_gpu, int) or per_gpu < 1):
        raise ValueError(f"--per-gpu must be auto or a number >= 1, got {per_gpu!r}")
    check_mps_mode(mps)
    devices = parse_gpus(gpus)
    cluster = slurm_options(executor, **(slurm or {}))  # before the plan loads: nothing is read or written
    if cluster is not None and plan_only:
        raise ValueError("--plan-only prints the commands for a scheduler of your own: leave out --executor slurm")
    if cluster is None and not (plan_only or worker or cell is not None):
        check_local_gpus(devices)  # the local pool's workers take these GPUs
    check_output_folder(out, "--out")
    check_reuse_dirs(reuse or [])  # here, not only when the cells run: --plan-only and --cell too
    plan = load_plan(plan_name, overrides)
    if cell is not None and patterns:
        raise ValueError("--cell runs one cell, --cells those matching patterns: give one of them")
    if cell is not None:
        plan.cell(cell)  # an unknown --cell is refused on every path, --plan-only and --worker included
    if worker:
        return cell_worker(plan, Path(out), progress)
    chosen_cells = [plan.cell(cell)] if cell is not None else plan.select(patterns or [])
    reuse_dirs = [Path(path) for path in reuse or []]
    folds = fold_lines(fold_sizes(plan))
    if plan_only:
        from warpsense.study.adaptive import plan_only_notes

        print("\n".join([*(f"# {line}" for line in folds), *(f"# {line}" for line in plan_only_notes(plan)),
                         *plan_commands(plan, Path(out), reuse_dirs, chosen_cells)]))
        return 0
    if plan.search is not None and cell is None and not patterns:
        from warpsense.study.search import require_optuna

        require_optuna()  # before anything is written
    check_runnable(plan, chosen_cells, local=cluster is None)  # a device it cannot have: before anything is written
    print("\n".join(f"study: {line}" for line in folds), flush=True)
    # study.sequential and [[search]] choose their rounds of cells (warpsense.study.adaptive); --cell and --cells
    # run the cells named, as in any plan
    adaptive = (plan.sequential is not None or plan.search is not None) and cell is None and not patterns
    if adaptive:
        from warpsense.study.adaptive import run_adaptive
    if cluster is not None and adaptive:
        return run_adaptive(plan, Path(out), lambda round_plan, cells: submit_study(round_plan, Path(out), cluster,
                                                                                    cells, reuse_dirs),
                            wait=cluster.wait)
    if cluster is not None:
        return submit_study(plan, Path(out), cluster, None if cell is None and not patterns else chosen_cells,
                            reuse_dirs)
    local = chosen_cells
    check_not_queued(Path(out), [each for each in local if StudyDir(Path(out)).cell_state(each) != "done"])
    if cell is not None:  # here, on this process's cuda:0 or the CPU; GPUs named without 0: a worker on the first
        elsewhere = devices[:1] if devices and "0" not in devices else None
        if elsewhere:
            check_local_gpus(devices)
        return run_cells(plan, Path(out), cells=local, gpus=elsewhere, mps="off",
                         progress=progress, record=False, reuse=reuse_dirs)
    return _run_pool(plan, out, local, devices, gpus, per_gpu, mps, progress, reuse_dirs, adaptive)


def _run_pool(plan, out: str, local: list, devices: list[str], gpus: str, per_gpu: int | str, mps: str,
              progress: bool, reuse_dirs: list[Path], adaptive: bool) -> int:
    """`run_study`'s local path for the cells ``local``: the pool over ``devices`` (``gpus``: what --gpus said), or
    this process; with ``adaptive``, round after round (`warpsense.study.adaptive.run_adaptive`)."""
    from warpsense.study.mps import MPSError
    from warpsense.study.runner import run_cells

    def run_pool(per_gpu: int, mps: str, round_plan=plan, cells=None) -> int:
        # in this process where that is one cell at a time on its own cuda:0 (or the CPU); one worker process
        # for another single GPU (--gpus 1): this process's training would take cuda:0 whatever --gpus says
        here = not devices or (devices == ["0"] and per_gpu == 1)
        return run_cells(round_plan, Path(out), cells=local if cells is None else cells,
                         gpus=None if here else devices, per_gpu=per_gpu, progress=progress, sample_gpus=devices,
                         reuse=reuse_dirs, mps=mps)

    chosen = per_gpu == "auto"
    if not devices and (mps == "on" or per_gpu not in ("auto", 1)):  # a GPU machine's command line, run on a CPU
        print(f"study: no pool of GPUs (--gpus {gpus}): the cells run one at a time in this process; --per-gpu and "
              "--mps apply to the pool", flush=True)

    def run_local(round_plan=plan, cells=None) -> int:
        try:
            return run_pool(pool_cells_per_gpu(plan, devices, mps) if chosen else per_gpu, mps, round_plan, cells)
        except MPSError as error:
            if not (chosen and mps == "auto"):
                raise
            # a choice of ours, not the user's: one cell a GPU without MPS rather than no study
            print(f"study: {error}; one cell at once on each GPU instead", file=sys.stderr, flush=True)
            return run_pool(1, "off", round_plan, cells)

    if adaptive:
        from warpsense.study.adaptive import run_adaptive
    code = run_adaptive(plan, Path(out), run_local) if adaptive else run_local()
    if code == 0:
        print(f"study finished; report: warpsense study report {out}")
    return code


def pool_cells_per_gpu(plan, devices: list[str], mps: str) -> int:
    """``--per-gpu auto`` for a local pool on ``devices`` (`warpsense.study.mps.auto_cells_per_gpu`), said in one
    line; 1 without GPUs."""
    from warpsense.study.gpus import gpu_memory_gib
    from warpsense.study.mps import auto_cells_per_gpu
    from warpsense.study.work import step_pixels

    if not devices:
        return 1
    count, why = auto_cells_per_gpu(mps, gpu_memory_gib(devices), step_pixels(plan))
    print(f"study: {count} cell(s) at once on each GPU (--per-gpu auto: {why}; --per-gpu N sets it)", flush=True)
    return count


def study_status(study_dir: str) -> int:
    """The `warpsense study status` command: each cell pending, running, done or failed."""
    from warpsense.study.slurm import print_status

    return print_status(study_dir)


def study_report(study_dir: str, json_out: str | None = None, plot_out: str | None = None,
                 split: str | None = None, resamples: int = 2000, block_frames: int = 10) -> int:
    """The `warpsense study report` command: console text, and the same record as JSON and a plot (with sweeps, and
    the design map beside it: OUT_map.png for ``--plot OUT.png``; with a search, its designs: OUT_search.png)."""
    from warpsense.study.report import plot_study, render_text, study_record

    if split is not None and not plot_out:
        raise ValueError(f"--split {split} picks the split --plot draws (the text and --json hold every split): "
                         "add --plot OUT.png")
    check_output_file(json_out, "--json")
    check_plot_file(plot_out, "--plot")
    record = study_record(study_dir, resamples, block_frames)
    if split is not None and split not in record["splits"]:
        raise ValueError(f"--split {split!r}: the study's runs were judged on {', '.join(record['splits'])}")
    print(render_text(record))
    if json_out:
        write_json(json_out, record)
        print(f"wrote {json_out}")
    if plot_out:
        plot_study(record, plot_out, split)
        print(f"wrote {plot_out}")
        if record["maps"]:  # a plan with sweeps: the design map beside the plot
            from warpsense.study.maps import map_path, plot_maps

            if plot_maps(record, map_path(plot_out), split):
                print(f"wrote {map_path(plot_out)}")
        if record.get("search"):  # a plan with a [[search]]: its designs over the searched keys beside it
            from warpsense.study.search_report import plot_search, search_path

            if plot_search(record, search_path(plot_out)):
                print(f"wrote {search_path(plot_out)}")
    return 0
