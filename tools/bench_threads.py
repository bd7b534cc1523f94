"""CPU training throughput under thread settings, alone and beside another CPU job on the same cores.

Each setting trains a short quickstart run (generated scenes, the default model and batch) in a fresh process, as
`warpsense train` would, and reports the training img/s of its last epoch (the first pays for Warp's kernel
compilation and torch's first calls). Beside a competing job means a second copy of the same run started at the same
time, pinned to the same cores: what "another CPU job" does to each setting.

    python tools/bench_threads.py                       # every setting, alone and contended, on this machine's cores
    taskset -c 0,1 python tools/bench_threads.py        # as on a 2-core machine (on a larger one)
    python tools/bench_threads.py --settings default,passive --repeats 3 --json threads.json

Settings (environment variables of the training process, read by torch's OpenMP runtime when it loads):
    default   the OpenMP runtime's own (libgomp: idle threads spin 300000 turns at each barrier), as a Python
              program that imports warpsense gets; the `warpsense` commands set PASSIVE (warpsense.cli)
    active    OMP_WAIT_POLICY=ACTIVE: idle OpenMP threads spin at barriers (libgomp's default spin time is long)
    passive   OMP_WAIT_POLICY=PASSIVE: idle OpenMP threads sleep at once
    one       OMP_NUM_THREADS=1: one intra-op thread
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SETTINGS = {
    "default": {},
    "active": {"OMP_WAIT_POLICY": "ACTIVE"},
    "passive": {"OMP_WAIT_POLICY": "PASSIVE"},
    "one": {"OMP_NUM_THREADS": "1"},
}

RUN = """
import json, sys, time
from warpsense.config import load_config
from warpsense.train.engine import train
import torch
config = load_config(None, sys.argv[2:] + [f"run.output_dir={sys.argv[1]}"])
started = time.perf_counter()
run = train(config, progress=False)
records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
print(json.dumps({"images_per_s": records[-1]["images_per_s"], "wall_s": time.perf_counter() - started,
                  "threads": torch.get_num_threads()}))
"""


def run_setting(name: str, contended: bool, overrides: list[str], folder: Path) -> dict:
    """One measurement: the setting's run alone, or beside a second copy started with it."""
    environment = {key: value for key, value in os.environ.items() if key not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")}
    environment.update(SETTINGS[name])
    copies = 2 if contended else 1
    processes = [subprocess.Popen([sys.executable, "-c", RUN, str(folder / f"{name}{copy}"), *overrides],
                                  env=environment, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for copy in range(copies)]
    results = []
    for process in processes:
        out, err = process.communicate()
        if process.returncode:
            raise SystemExit(f"bench_threads: the {name} run failed: {err.strip().splitlines()[-1]}")
        results.append(json.loads(out.strip().splitlines()[-1]))
    return {"setting": name, "contended": contended, "images_per_s": results[0]["images_per_s"],
            "wall_s": results[0]["wall_s"], "threads": results[0]["threads"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--settings", default=",".join(SETTINGS),
                        help=f"comma-separated, of {', '.join(SETTINGS)} (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=2,
                        help="measurements per setting and case (default: %(default)s)")
    parser.add_argument("--scenes", type=int, default=64, help="training scenes per epoch (default: %(default)s)")
    parser.add_argument("--json", metavar="OUT", help="write the measurements as JSON")
    args = parser.parse_args(argv)
    names = args.settings.split(",")
    unknown = [name for name in names if name not in SETTINGS]
    if unknown:
        parser.error(f"--settings: unknown {unknown[0]!r}; settings: {', '.join(SETTINGS)}")
    overrides = ["run.device=cpu", f"data.scenes_train={args.scenes}", "data.scenes_val=8", "train.epochs=2",
                 "train.warmup_epochs=1", "train.plots=false"]
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for repeat in range(args.repeats):  # interleaved, so that a drift in the machine's load spreads over all
            for contended in (False, True):
                for name in names:
                    row = run_setting(name, contended, overrides, Path(folder) / f"r{repeat}{int(contended)}")
                    rows.append(row)
                    print(f"{name:>8s}  {'contended' if contended else 'alone':>9s}  {row['images_per_s']:7.1f} img/s"
                          f"  ({row['threads']} threads)", flush=True)
    print(f"\n{'setting':>8s}  {'alone':>14s}  {'contended':>14s}  (median img/s [min, max] of {args.repeats})")
    for name in names:
        cells = []
        for contended in (False, True):
            values = [r["images_per_s"] for r in rows if r["setting"] == name and r["contended"] == contended]
            cells.append(f"{statistics.median(values):5.1f} [{min(values):.1f}, {max(values):.1f}]")
        print(f"{name:>8s}  {cells[0]:>14s}  {cells[1]:>14s}")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "cpu_count": os.cpu_count(),
                                               "affinity": sorted(os.sched_getaffinity(0)),
                                               "time": time.strftime("%Y-%m-%d %H:%M:%S")}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
