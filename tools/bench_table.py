"""Markdown tables for docs/benchmarks.md from `warpsense bench --suite train|accuracy --json` output.

    python tools/bench_table.py BENCH_JSON [--out FILE]

Training rows: method, camera, loss, step mode (eager / graph / compiled / compiled + graph), images per second and
the ratio to the plain-torch baseline measured in the same run with the same loss and step mode (the only ratio the
suite supports: figures from different runs are not comparable). Latency rows: batch-1 median milliseconds, eager
and CUDA-graph replay, with the baseline's time divided by the row's (above 1 = faster than the baseline). Failed
records (a compiler error, say) appear with their error. The device named in the JSON heads the tables.

Accuracy rows (error against run time): per kernel and method the L2-relative and 99th-percentile pointwise
relative errors on each scene and the forward, backward and forward + backward milliseconds; the quantizer's
code-flip rates per bit depth; the lens axes with each setting's error against the converged reference and against
the next finer setting, with what the setting costs (PSF render + convolution forward + backward).
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
    everything = payload.get("records", [])
    records = [r for r in everything if r.get("suite") == "train"]
    accuracy = [r for r in everything if r.get("suite") == "accuracy"]
    if not records and not accuracy:
        raise ValueError("no train-suite or accuracy records "
                         "(run `warpsense bench --suite train|accuracy --json FILE`)")
    metadata = payload.get("metadata", {})
    first = (records or accuracy)[0]
    header = [f"Device: {metadata.get('device_name') or first.get('device_name') or first['device']} "
              f"(torch {metadata.get('torch', '?')}, warp {metadata.get('warp', '?')})", ""]
    if not records:
        return "\n".join(header + accuracy_tables(accuracy)) + "\n"
    lines = header + ["| method | camera | loss | step | img/s | vs baseline, same loss and step |",
                      "|---|---|---|---|---|---|"]
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
            speedup = reference.get(record["mode"].removesuffix("_cached"))  # the baseline has no camera to cache
            speedup = f"{speedup / record['median_ms']:.2f}" if speedup else "-"
            lines.append(f"| {record['method']} | {record['camera']} | {record['mode']} | {record['median_ms']:.3f} | "
                         f"{speedup} |")
    if accuracy:
        lines += [""] + accuracy_tables(accuracy)
    return "\n".join(lines) + "\n"


def _number(value, spec: str = ".2g") -> str:
    return "-" if value is None else format(value, spec)


def accuracy_tables(records: list[dict]) -> list[str]:
    """The kernels' errors and times, the quantizer's code flips, and the lens axes' convergence (markdown lines)."""
    scenes = list(dict.fromkeys(r["scene"] for r in records))
    by_case: dict[tuple, dict] = {}
    for record in records:
        by_case.setdefault((record["kernel"], record["method"]), {})[record["scene"]] = record
    threads = records[0].get("threads", "?")
    lines = [f"Errors against float64 references; times are medians from torch.utils.benchmark ({threads} torch "
             f"threads), ms. Scenes: {', '.join(scenes)}.", "",
             "| kernel | method | L2 rel: " + " / ".join(scenes) + " | p99 pointwise rel: " + " / ".join(scenes)
             + " | max rel (" + scenes[-1] + ") | fwd | bwd | fwd+bwd |", "|---|---|---|---|---|---|---|---|"]
    for (kernel, method), rows in by_case.items():
        if kernel.startswith("lens_") or kernel == "quantize_ste":
            continue
        any_row = next(iter(rows.values()))
        lines.append(f"| {kernel} | {method} | " + " / ".join(_number(rows[s]["l2_rel_err"]) for s in scenes)
                     + " | " + " / ".join(_number(rows[s]["p99_rel_err"]) for s in scenes)
                     + f" | {_number(rows[scenes[-1]]['max_rel_err'])} | {_number(any_row.get('fwd_ms'), '.3f')} | "
                     f"{_number(any_row.get('bwd_ms'), '.3f')} | {_number(any_row.get('fwd_bwd_ms'), '.3f')} |")
    quantizer = [(method, rows) for (kernel, method), rows in by_case.items() if kernel == "quantize_ste"]
    if quantizer:
        lines += ["", "| quantizer | code-flip rate: " + " / ".join(scenes) + " | fwd+bwd ms |", "|---|---|---|"]
        for method, rows in quantizer:
            any_row = next(iter(rows.values()))
            lines.append(f"| {method} | " + " / ".join(_number(rows[s]["code_flip_rate"]) for s in scenes)
                         + f" | {_number(any_row.get('fwd_bwd_ms'), '.3f')} |")
    lens = [(kernel, method, rows) for (kernel, method), rows in by_case.items() if kernel.startswith("lens_")]
    if lens:
        lines += ["", "| lens axis | setting | L2 rel vs converged: " + " / ".join(scenes) + " | p99 vs converged: "
                  + " / ".join(scenes) + " | L2 vs next finer (" + scenes[0] + ") | render + conv fwd+bwd ms | "
                  "energy outside K, of the converged window |", "|---|---|---|---|---|---|---|"]
        for kernel, _method, rows in lens:
            any_row = next(iter(rows.values()))
            cost = ("converged reference" if any_row.get("converged") else
                    f"{_number(any_row.get('render_ms'), '.1f')} + {_number(any_row.get('conv_fwd_bwd_ms'), '.1f')}")
            lines.append(f"| {kernel.removeprefix('lens_')} | {any_row['setting']} | "
                         + " / ".join(_number(rows[s]["l2_rel_err"]) for s in scenes) + " | "
                         + " / ".join(_number(rows[s]["p99_rel_err"]) for s in scenes)
                         + f" | {_number(rows[scenes[0]].get('vs_next_finer'))} | {cost} | "
                         f"{_number(any_row.get('energy_outside'), '.2g')} |")
    return lines


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", help="bench JSON written by `warpsense bench --suite train|accuracy --json`")
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
