"""The error-against-run-time report: its error norms, code-flip rate, scenes, lens convergence records, frontier,
console lines and plot."""

import json

import numpy as np
import pytest
import torch

from warpsense.bench import accuracy
from warpsense.bench.accuracy import (
    AccuracyBench,
    code_flip_rate,
    error_norms,
    format_record,
    make_scenes,
    pareto_frontier,
    plot_accuracy,
)
from warpsense.cli import main


def test_error_norms_match_numpy_formulas():
    generator = np.random.default_rng(0)
    reference = generator.uniform(0.5, 2.0, 1000)
    reference[:20] = 1e-9  # 2% dark values: only the pointwise norm sees their error
    output = reference * (1 + generator.normal(0, 1e-3, 1000))
    output[:20] = 2e-9
    errors = error_norms(torch.from_numpy(output), torch.from_numpy(reference))
    difference = np.abs(output - reference)
    assert errors["max_rel_err"] == pytest.approx(difference.max() / np.abs(reference).max())
    assert errors["l2_rel_err"] == pytest.approx(np.linalg.norm(difference) / np.linalg.norm(reference))
    assert errors["p99_rel_err"] == pytest.approx(np.quantile(difference / np.abs(reference), 0.99))
    assert errors["l2_rel_err"] < 2e-3 and errors["p99_rel_err"] > 0.5  # 2% of values 100% off: p99 tells


def test_pointwise_error_counts_a_zero_reference_against_the_floor():
    errors = error_norms(torch.tensor([1.0, 1e-20]), torch.tensor([1.0, 0.0]))
    assert errors["max_rel_err"] == pytest.approx(1e-20)
    assert errors["p99_rel_err"] == pytest.approx(0.99 * 1e-20 / accuracy.POINTWISE_FLOOR, rel=1e-6)


def test_code_flip_rate_counts_codes_not_values():
    raw = torch.tensor([0.1, 0.5, 0.9, 1.5, -1.0])
    exact = torch.floor(raw.double().clamp(0, 1) * 255 + 0.5) / 255
    assert code_flip_rate(exact.float(), raw, 8) == 0
    flipped = exact.clone()
    flipped[1] += 1 / 255
    assert code_flip_rate(flipped.float(), raw, 8) == pytest.approx(1 / 5)


def test_pareto_frontier_keeps_only_undominated_points():
    points = [(1.0, 0.5), (2.0, 0.6), (3.0, 0.1), (0.5, 0.9), (4.0, 0.1), (5.0, 0.01)]
    assert pareto_frontier(points) == [(0.5, 0.9), (1.0, 0.5), (3.0, 0.1), (5.0, 0.01)]


def test_scenes_cover_nine_decades_and_real_frames(shared_data):
    scenes = make_scenes(24, 32, "cpu", shared_data / "camvid", frames=2)
    assert set(scenes) == {"white_noise", "camvid", "hdr"}
    assert scenes["camvid"].shape == (2, 3, 24, 32) and scenes["camvid"].dtype == torch.float64
    assert 0 <= scenes["camvid"].min() and scenes["camvid"].max() <= 1 and scenes["camvid"].std() > 0.01
    hdr = scenes["hdr"]
    assert hdr.max() == 1e3 and hdr.min() < 2e-6 and (hdr == 1e3).float().mean() < 0.2
    assert "camvid" not in make_scenes(8, 8, "cpu")


def test_lens_axis_records_converge_and_print_what_they_hold(capsys):
    """One tiny axis end to end: the converged setting has zero error, each other one an error against it and
    against the next finer one, and the console line is printed from the very record the JSON gets."""
    bench = AccuracyBench("cpu", min_run_time=0.01)
    scenes = make_scenes(16, 24, "cpu")
    accuracy._lens_axes(bench, scenes, {"pixel_integration": ("oversampling", (1,), 3)})
    rows = {(r["setting"], r["scene"]): r for r in bench.records}
    assert len(rows) == 2 * len(scenes)
    for scene in scenes:
        coarse, converged = rows[(1, scene)], rows[(3, scene)]
        assert converged["converged"] and converged["l2_rel_err"] == 0 and "render_ms" not in converged
        assert 0 < coarse["l2_rel_err"] < 0.1 and coarse["vs_next_finer"] == pytest.approx(coarse["l2_rel_err"])
        assert coarse["fwd_bwd_ms"] == pytest.approx(coarse["render_ms"] + coarse["conv_fwd_bwd_ms"])
    printed = capsys.readouterr().out.splitlines()
    assert printed == [format_record(record) for record in bench.records]
    hdr = bench.records.index(rows[(1, "hdr")])
    assert f"l2 {rows[(1, 'hdr')]['l2_rel_err']:9.3g}" in printed[hdr]
    json.dumps(bench.records)  # what the JSON holds


def test_quantizer_rows_report_no_flips_for_the_warp_kernel():
    bench = AccuracyBench("cpu", min_run_time=0.01)
    scenes = {"white_noise": torch.rand(1, 3, 64, 64, dtype=torch.float64)}
    accuracy._pointwise_kernels(bench, scenes, quick=True)
    flips = {r["method"]: r["code_flip_rate"] for r in bench.records if r["kernel"] == "quantize_ste"}
    assert all(flips[f"warp_{bits}bit"] == 0 for bits in (8, 10, 12, 20, 24))
    assert flips["torch_float32_24bit"] > 0.01  # float32 arithmetic: the rate the warp kernel avoids
    cfa = [r for r in bench.records if r["kernel"] == "cfa_mosaic"]
    assert all(r["l2_rel_err"] < 1e-6 and r["fwd_ms"] > 0 and r["bwd_ms"] > 0 for r in cfa)


def test_plot_has_one_panel_per_kernel(tmp_path):
    records = [{"suite": "accuracy", "device": "cpu", "threads": 2, "kernel": kernel, "method": method,
                "scene": "white_noise", "fwd_bwd_ms": time_ms, "l2_rel_err": error, "code_flip_rate": error}
               for kernel in ("psf_conv", "quantize_ste") for method, time_ms, error in
               (("a", 1.0, 0.1), ("b", 2.0, 0.0))]
    path = tmp_path / "pareto.png"
    import matplotlib.pyplot as plt

    kept, close = [], plt.close
    plt.close = kept.append
    try:
        plot_accuracy(records, path)
    finally:
        plt.close = close
    assert path.stat().st_size > 10_000
    psf_axis, quantize_axis = kept[0].axes
    for axis in (psf_axis, quantize_axis):
        labels = [t.get_text() for t in axis.get_yticklabels()]
        assert labels[0] == "exact (0)"  # method b's zero error sits on the labelled line, not at a number
        legend = axis.get_legend()  # below the panel: it hides no point
        assert legend.get_bbox_to_anchor().y1 < axis.get_window_extent().y0 + 1
    close(kept[0])
    with pytest.raises(ValueError, match="no accuracy records"):
        plot_accuracy([{"suite": "train"}], tmp_path / "none.png")


def test_cli_refuses_a_plot_without_the_accuracy_suite_and_a_folder_without_val(tmp_path, capsys):
    assert main(["bench", "--suite", "kernels", "--plot", str(tmp_path / "p.png")]) != 0
    assert "--suite accuracy" in capsys.readouterr().err
    assert main(["bench", "--suite", "accuracy", "--camvid", str(tmp_path)]) != 0
    assert "val.txt" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_kernel_table_has_headers_and_the_spread(capsys):
    from warpsense.bench.runner import Bench

    bench = Bench("cpu", repeats=1)
    bench.record("cfa", "warp", "float32", (1, 3, 8, 8), "fwd", {"median_ms": 1.25, "iqr_ms": 0.5},
                 {"max_abs_err": 0.0, "max_rel_err": 1e-7})
    bench.record("cfa", "warp", "float32", (1, 3, 8, 8), "bwd", {"median_ms": 2.0, "iqr_ms": 0.25})
    header, first, second = capsys.readouterr().out.splitlines()
    assert header.split() == ["kernel", "method", "dtype", "shape", "pass", "median", "ms", "IQR", "ms", "max", "rel",
                              "err"]
    assert first.split()[-3:] == ["1.250", "0.500", "1e-07"] and second.split()[-3:] == ["2.000", "0.250", "-"]
