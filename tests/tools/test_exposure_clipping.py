"""tools/exposure_clipping.py: clipping that can only grow with the gain on real CamVid frames, and its refusals."""

import json

import pytest


@pytest.fixture
def tool(load_tool):
    return load_tool("exposure_clipping")


@pytest.mark.parametrize("gains", ["1,4", "0.25", "two"])
def test_bad_gains_are_one_line_errors(tool, gains, capsys):
    with pytest.raises(SystemExit) as exit_info:
        tool.main(["--gains", gains])
    assert exit_info.value.code == 2
    assert f"--gains {gains!r}:" in capsys.readouterr().err


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
