"""Markdown tables for docs/benchmarks.md from `warpsense bench --suite train --json` output.

    python tools/bench_table.py BENCH_JSON [--out FILE]

Training rows: method, camera, loss, step mode (eager / graph / compiled / compiled + graph), images per second and
the ratio to the plain-torch baseline measured in the same run with the same loss and step mode (the only ratio the
suite supports: figures from different runs are not comparable). Latency rows: batch-1 median milliseconds, eager
and CUDA-graph replay, with the baseline's time divided by the row's (above 1 = faster than the baseline). Failed
records (a compiler error, say) appear with their error. The device named in the JSON heads the tables.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

BASELINE = "torch_baseline"


def step_mode(record: dict) -> str:
    compiled = record.get("compile", "off") != "off"
    graph = bool(record.get("cuda_graph"))
    return {(False, False): "eager", (False, True): "graph", (True, False): "compiled",
            (True, True): "compiled + graph"}[(compiled, graph)]


def tables(payload: dict) -> str:
    records = [r for r in payload.get("records", []) if r.get("suite") == "train"]
    if not records:
        raise ValueError("no train-suite records (run `warpsense bench --suite train --json FILE`)")
    metadata = payload.get("metadata", {})
    lines = [f"Device: {metadata.get('device_name') or records[0].get('device_name') or records[0]['device']} "
             f"(torch {metadata.get('torch', '?')}, warp {metadata.get('warp', '?')})", "",
             "| method | camera | loss | step | img/s | vs baseline, same loss and step |", "|---|---|---|---|---|---|"]
    training = [r for r in records if "loss" in r]
    baseline = {(r["loss"], step_mode(r)): r.get("images_per_s") for r in training if r["method"] == BASELINE}
    for record in training:
        mode = step_mode(record)
        if "images_per_s" not in record:
            lines.append(f"| {record['method']} | {record['camera']} | {record['loss']} | {mode} | "
                         f"failed: {record.get('error', '?')} | - |")
            continue
        reference = baseline.get((record["loss"], mode))
        ratio = f"{record['images_per_s'] / reference:.2f}" if reference else "-"
        lines.append(f"| {record['method']} | {record['camera']} | {record['loss']} | {mode} | "
                     f"{record['images_per_s']:.1f} | {ratio} |")
    latency = [r for r in records if "mode" in r and "median_ms" in r]
    if latency:
        reference = {r["mode"]: r["median_ms"] for r in latency if r["method"] == BASELINE and r["camera"] == "simple"}
        lines += ["", "| method | camera | batch-1 | median ms | baseline ms / this |", "|---|---|---|---|---|"]
        for record in latency:
            speedup = reference.get(record["mode"])
            speedup = f"{speedup / record['median_ms']:.2f}" if speedup else "-"
            lines.append(f"| {record['method']} | {record['camera']} | {record['mode']} | {record['median_ms']:.3f} | "
                         f"{speedup} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", help="bench JSON written by `warpsense bench --suite train --json`")
    parser.add_argument("--out", help="also write the tables to this file")
    args = parser.parse_args(argv)
    try:
        payload = json.loads(Path(args.json).read_text())
        text = tables(payload)
    except (OSError, ValueError) as error:
        raise SystemExit(f"bench_table: {args.json}: {error}") from None
    print(text, end="")
    if args.out:
        Path(args.out).write_text(text)
    return text


if __name__ == "__main__":
    main()
