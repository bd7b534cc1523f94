from pathlib import Path

import pytest
from PIL import Image


@pytest.fixture
def tool(load_tool):
    return load_tool("checkpoint_figures")


def test_figures_of_a_shipped_checkpoint_and_a_bad_one_reported(tool, shared_data, tmp_path, capsys):
    checkpoint = Path(__file__).resolve().parents[2] / "checkpoints" / "camvid_codesign.safetensors"
    bad = tmp_path / "broken.safetensors"
    bad.write_bytes(b"not a checkpoint")
    out_dir = tmp_path / "img"
    status = tool.main([str(bad), str(checkpoint), "--data-root", str(shared_data / "camvid"), "--out-dir",
                        str(out_dir), "--count", "2"])
    assert status == 1  # the bad checkpoint fails, the good one is still drawn
    captured = capsys.readouterr()
    assert str(bad) in captured.err and len(captured.err.strip().splitlines()) == 1
    written = sorted(p.name for p in out_dir.iterdir())
    assert written == ["camvid_codesign_camera.png", "camvid_codesign_predictions.png"]
    camera = Image.open(out_dir / "camvid_codesign_camera.png")
    predictions = Image.open(out_dir / "camvid_codesign_predictions.png")
    assert camera.width > camera.height  # two panels side by side: the PSF grid and the CFA
    assert predictions.height > 0.4 * predictions.width  # two rows of four panels and the legend
