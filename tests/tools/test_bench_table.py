import json

import pytest


@pytest.fixture
def tool(load_tool):
    return load_tool("bench_table")


def test_ratios_are_to_the_baseline_of_the_same_loss_and_step(tool, tmp_path):
    def training(method, camera, rate, compile_mode="off", graph=False, **extra):
        record = {"suite": "train", "device": "cuda", "method": method, "camera": camera, "loss": "full",
                  "compile": compile_mode, "cuda_graph": graph, **extra}
        if rate is not None:
            record["images_per_s"] = rate
        return record

    records = [training("torch_baseline", "simple", 400.0), training("warpsense", "simple", 500.0),
               training("torch_baseline", "simple", 800.0, "default", True),
               training("warpsense", "codesign", 600.0, "default", True),
               training("warpsense", "codesign", None, "default", False, error="InductorError: boom"),
               {"suite": "train", "device": "cuda", "method": "torch_baseline", "camera": "simple", "mode": "graph",
                "median_ms": 2.0},
               {"suite": "train", "device": "cuda", "method": "warpsense", "camera": "simple", "mode": "graph",
                "median_ms": 1.0}]
    path = tmp_path / "bench.json"
    path.write_text(json.dumps({"metadata": {"device_name": "Test GPU", "torch": "x", "warp": "y"}, "records": records}))
    lines = tool.main([str(path)]).splitlines()
    assert lines[0].startswith("Device: Test GPU")
    assert "| warpsense | simple | full | eager | 500.0 | 1.25 |" in lines
    assert "| warpsense | codesign | full | compiled + graph | 600.0 | 0.75 |" in lines  # against 800, not 400
    assert "| warpsense | codesign | full | compiled | failed: InductorError: boom | - |" in lines
    assert "| warpsense | simple | graph | 1.000 | 2.00 |" in lines


def test_a_file_without_train_records_is_a_one_line_error(tool, tmp_path):
    path = tmp_path / "kernels.json"
    path.write_text(json.dumps({"records": [{"suite": "kernels"}]}))
    with pytest.raises(SystemExit, match="no train-suite records"):
        tool.main([str(path)])
