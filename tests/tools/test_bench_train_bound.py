import json

import pytest

TINY = ["--set", "train.compile=off", "--set", "train.cuda_graph=false", "--set", "model.width=8",
        "--device", "cpu", "--size", "16x24", "--batch", "2", "--steps", "1"]


@pytest.fixture
def tool(load_tool):
    return load_tool("bench_train_bound")


def test_three_variants_measured_and_written(tool, tmp_path, capsys):
    out = tmp_path / "bound.json"
    assert tool.main(["--config", "camvid_codesign", *TINY, "--json", str(out)]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    result = json.loads(out.read_text())
    assert result["records"] == lines and result["device"] == "cpu"
    assert [r["variant"] for r in lines] == ["network only, cross-entropy", "network only, the config's losses",
                                            "camera + network, the config's losses"]
    assert all(r["images_per_s"] > 0 and r["size"] == [16, 24] for r in lines)
    assert "loss.lovasz_weight=0" in lines[0]["overrides"] and "loss.lovasz_weight=0" not in lines[1]["overrides"]


def test_bad_size_and_bad_override_are_one_line_errors(tool, capsys):
    with pytest.raises(SystemExit):
        tool.main(["--size", "352"])
    assert "--size must be HxW" in capsys.readouterr().err
    assert tool.main(["--set", "train.no_such_key=1", "--device", "cpu"]) == 2
    assert "no_such_key" in capsys.readouterr().err


def test_variants_picks_some_in_the_order_given_and_rejects_unknown_names(tool, capsys):
    assert tool.main(["--config", "camvid_codesign", *TINY, "--variants", "step,ce"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["variant"] for r in lines] == ["camera + network, the config's losses", "network only, cross-entropy"]
    with pytest.raises(SystemExit):
        tool.main(["--variants", "ce,whole"])
    assert "--variants: unknown whole; valid: ce, loss, step" in capsys.readouterr().err
