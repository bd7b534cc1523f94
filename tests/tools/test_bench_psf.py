import json


def test_bench_psf_quick_on_cpu_reports_every_method_and_a_correct_kernel(tmp_path, capsys, load_tool):
    tool = load_tool("bench_psf")
    report = tool.main(["--device", "cpu", "--quick", "--json", str(tmp_path / "psf.json")])
    assert {row["method"] for row in report["rows"]} == set(tool.METHODS)
    assert all(row["fwd_bwd_ms"] > 0 for row in report["rows"])
    assert max(report["varying_float64_max_error"].values()) < 1e-10
    assert json.loads((tmp_path / "psf.json").read_text())["rows"] == report["rows"]
    assert "x cuDNN" in capsys.readouterr().out
