"""`warpsense study run | report`: run a study plan's cells, and report what they say."""

from __future__ import annotations

from pathlib import Path

from warpsense.files import check_output_file, check_output_folder, write_json


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


def run_study(plan_name: str, out: str, overrides: list[str], cell: str | None = None, plan_only: bool = False,
              gpus: str = "auto", per_gpu: int = 1, progress: bool = False, worker: bool = False,
              reuse: list[str] | None = None, executor: str = "local", slurm: dict | None = None,
              mps: str = "auto") -> int:
    """The `warpsense study run` command; returns the exit code. ``worker``: be one of the local pool's worker
    processes (`warpsense.study.runner.cell_worker`, cell ids on stdin). ``executor`` "slurm": submit the cells to
    Slurm (`warpsense.study.slurm.submit_study`) with ``slurm``, the keyword arguments of
    `warpsense.study.slurm.slurm_options` (None: not given)."""
    from warpsense.study.mps import check_mode as check_mps_mode
    from warpsense.study.plan import load_plan
    from warpsense.study.runner import cell_worker, check_reuse_dirs, plan_commands, run_cells
    from warpsense.study.slurm import slurm_options, submit_study

    # every option is checked here, whichever path follows (worker, plan-only, one cell, pool, Slurm)
    if per_gpu < 1:
        raise ValueError(f"--per-gpu must be >= 1, got {per_gpu}")
    check_mps_mode(mps)
    devices = parse_gpus(gpus)
    cluster = slurm_options(executor, **(slurm or {}))  # before the plan loads: nothing is read or written
    if cluster is not None and plan_only:
        raise ValueError("--plan-only prints the commands for a scheduler of your own: leave out --executor slurm")
    check_output_folder(out, "--out")
    check_reuse_dirs(reuse or [])  # here, not only when the cells run: --plan-only and --cell too
    plan = load_plan(plan_name, overrides)
    if cell is not None:
        plan.cell(cell)  # an unknown --cell is refused on every path, --plan-only and --worker included
    if worker:
        return cell_worker(plan, Path(out))
    if plan_only:
        print("\n".join(plan_commands(plan, Path(out))))
        return 0
    reuse_dirs = [Path(path) for path in reuse or []]
    if cluster is not None:
        return submit_study(plan, Path(out), cluster, None if cell is None else [plan.cell(cell)], reuse_dirs)
    if cell is not None:
        return run_cells(plan, Path(out), [plan.cell(cell)], progress=progress, record=False, reuse=reuse_dirs)
    code = run_cells(plan, Path(out), gpus=devices if len(devices) * per_gpu > 1 else None, per_gpu=per_gpu,
                     progress=progress, sample_gpus=devices, reuse=reuse_dirs, mps=mps)
    if code == 0:
        print(f"study finished; report: warpsense study report {out}")
    return code


def status_study(study_dir: str) -> int:
    """The `warpsense study status` command: each cell pending, running, done or failed."""
    from warpsense.study.slurm import print_status

    return print_status(study_dir)


def report_study(study_dir: str, json_out: str | None = None, plot_out: str | None = None,
                 split: str | None = None, resamples: int = 2000, block_frames: int = 10) -> int:
    """The `warpsense study report` command: console text, and the same record as JSON and a plot (with sweeps, and
    the design map beside it: OUT_map.png for ``--plot OUT.png``)."""
    from warpsense.study.report import plot_study, render_text, study_record

    check_output_file(json_out, "--json")
    check_output_file(plot_out, "--plot")
    record = study_record(study_dir, resamples, block_frames)
    if split is not None and split not in record["splits"]:
        raise ValueError(f"--split {split!r}: the study's runs were judged on {', '.join(record['splits'])}")
    print(render_text(record))
    if json_out:
        write_json(json_out, record)
    if plot_out:
        plot_study(record, plot_out, split)
        print(f"wrote {plot_out}")
        if record["maps"]:  # a plan with sweeps: the design map beside the plot
            from warpsense.study.maps import map_path, plot_maps

            if plot_maps(record, map_path(plot_out), split):
                print(f"wrote {map_path(plot_out)}")
    return 0
