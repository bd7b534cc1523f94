import json

import pytest


@pytest.fixture
def tool(load_tool):
    return load_tool("bench_camera_parts")


def test_floor_counts_two_and_three_instructions_per_output_and_tap(tool):
    floor = tool.floor_ms(outputs=1_000_000, kernel_size=15, peak_tops=1.0)
    # 1e6 outputs x 225 taps x 2 (forward) / 3 (PSF gradient) instructions at 1e12 per second
    assert floor["forward"] == pytest.approx(0.45) and floor["psf_gradient"] == pytest.approx(0.675)


def test_parts_timed_and_written(tool, tmp_path, capsys):
    out = tmp_path / "parts.json"
    assert tool.main(["--device", "cpu", "--size", "16x24", "--batch", "1", "--repeats", "1", "--json",
                      str(out)]) == 0
    result = json.loads(out.read_text())
    assert list(result["parts"]) == ["camera", "rendering", "psf_conv", "psf_forward", "baseline"]
    assert all(part["median_ms"] > 0 for part in result["parts"].values())
    assert result["psf_grid"][0] == 3 and result["mode"] == "eager"
    assert result["floor_ms"]["forward"] == pytest.approx(1 * 3 * 16 * 24 * result["psf_grid"][-1] ** 2 * 2
                                                         / 33.5e12 * 1e3)
    assert "camera / baseline" in capsys.readouterr().out


def test_bad_arguments_are_one_line_errors(tool, capsys):
    for argv, message in ((["--size", "16"], "--size must be HxW"), (["--peak-tops", "0"], "--peak-tops must be > 0")):
        with pytest.raises(SystemExit):
            tool.main(argv)
        assert message in capsys.readouterr().err
