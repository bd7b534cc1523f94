"""tools/exposure_clipping.py: the gain <-> logit map against the camera's own exposure stage, clipping that can only
grow with the gain on real CamVid frames, and its refusals."""

import json

import pytest

from warpsense.camera import Camera
from warpsense.config import load_config


@pytest.fixture
def tool(load_tool):
    return load_tool("exposure_clipping")


@pytest.mark.parametrize("gain", [0.5, 1.0, 2.0, 3.0])
def test_gain_logit_gives_the_camera_that_gain(tool, gain):
    camera = Camera.from_config(load_config("camvid_codesign", [f"exposure.gain_logit={tool.gain_logit(gain)}"]))
    assert camera.learned().exposure_gain == pytest.approx(gain, rel=1e-5)


def test_exception_outside_the_exposure_range(tool):
    for gain in (0.25, 4.0, 5.0):
        with pytest.raises(ValueError, match="outside the exposure stage's range"):
            tool.gain_logit(gain)


def test_clipping_grows_with_the_gain_on_camvid(tool, shared_data, tmp_path, capsys):
    out = tmp_path / "clip.json"
    tool.main(["--data-root", str(shared_data / "camvid"), "--gains", "0.5,1,3", "--limit", "2", "--json", str(out)])
    records = json.loads(out.read_text())
    assert [r["gain"] for r in records] == [0.5, 1.0, 3.0]
    shares = [r["all"] for r in records]
    assert 0 <= shares[0] <= shares[1] <= shares[2] <= 1
    assert shares[2] > shares[0]  # tripling the light of a daylight frame clips something
    for low, high in zip(records, records[1:]):
        for name, share in low["classes"].items():
            if share is not None:
                assert share <= high["classes"][name]
    assert "gain 3: " in capsys.readouterr().out
