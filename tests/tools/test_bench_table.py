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
                "median_ms": 1.0},
               {"suite": "train", "device": "cuda", "method": "torch_baseline", "camera": "simple", "mode": "eager",
                "median_ms": 6.0},
               {"suite": "train", "device": "cuda", "method": "warpsense", "camera": "codesign",
                "mode": "eager_cached", "median_ms": 5.0}]
    path = tmp_path / "bench.json"
    metadata = {"device_name": "Test GPU", "torch": "x", "warp": "y"}
    path.write_text(json.dumps({"metadata": metadata, "records": records}))
    lines = tool.main([str(path)]).splitlines()
    assert lines[0].startswith("Device: Test GPU")
    assert "| warpsense | simple | full | eager | 500.0 | 1.25 |" in lines
    assert "| warpsense | codesign | full | compiled + graph | 600.0 | 0.75 |" in lines  # against 800, not 400
    assert "| warpsense | codesign | full | compiled | failed: InductorError: boom | - |" in lines
    assert "| warpsense | simple | graph | 1.000 | 2.00 |" in lines
    assert "| warpsense | codesign | eager_cached | 5.000 | 1.20 |" in lines  # against the baseline's eager call


def test_a_file_without_train_records_is_a_one_line_error(tool, tmp_path):
    path = tmp_path / "kernels.json"
    path.write_text(json.dumps({"records": [{"suite": "kernels"}]}))
    with pytest.raises(SystemExit, match="no train-suite or accuracy records"):
        tool.main([str(path)])


def test_accuracy_tables_from_records(tool, tmp_path):
    def record(kernel, method, scene, **values):
        return {"suite": "accuracy", "device": "cuda", "threads": 16, "kernel": kernel, "method": method,
                "scene": scene, **values}

    errors = {"l2_rel_err": 2e-7, "p99_rel_err": 7e-7, "max_rel_err": 1e-6, "fwd_ms": 0.2, "bwd_ms": 1.0,
              "fwd_bwd_ms": 1.5}
    records = [record("psf_conv", "warp", scene, **errors) for scene in ("white_noise", "hdr")]
    records += [record("quantize_ste", "warp_10bit", scene, code_flip_rate=0.0, fwd_bwd_ms=0.4)
                for scene in ("white_noise", "hdr")]
    records += [record("lens_psf_grid", f"psf_grid={g}", scene, setting=g, converged=g == 17, l2_rel_err=e,
                       p99_rel_err=e, **({"vs_next_finer": e, "render_ms": 10.0, "conv_fwd_bwd_ms": 2.5} if g == 5
                                         else {}))
                for g, e in ((5, 0.008), (17, 0.0)) for scene in ("white_noise", "hdr")]
    path = tmp_path / "accuracy.json"
    path.write_text(json.dumps({"metadata": {"device_name": "Test GPU"}, "records": records}))
    text = tool.main([str(path)])
    assert text.startswith("Device: Test GPU")
    assert "| psf_conv | warp | 2e-07 / 2e-07 | 7e-07 / 7e-07 | 1e-06 | 0.200 | 1.000 | 1.500 |" in text
    assert "| warp_10bit | 0 / 0 | 0.400 |" in text
    assert "| psf_grid | 5 | 0.008 / 0.008 | 0.008 / 0.008 | 0.008 | 10.0 + 2.5 | - |" in text
    assert "| psf_grid | 17 | 0 / 0 | 0 / 0 | - | converged reference | - |" in text
