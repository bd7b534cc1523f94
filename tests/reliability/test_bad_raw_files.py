"""Raw captures that cannot be converted: empty, random, text, truncated at several points, other formats named
.dng, folders and missing paths. `warpsense convert` reports each in one line naming it, exits non-zero and writes
no output for it (issue 14, item 4); the batch case lives in tests/data/test_raw.py."""

import io

import numpy as np
import pytest
from PIL import Image

from tests.data.test_raw import _simulated_dng
from tests.reliability.conftest import assert_clean_failure


def _content(kind, tmp_path):
    if kind.startswith("truncated"):
        whole = _simulated_dng(tmp_path / "whole.dng").read_bytes()
        (tmp_path / "whole.dng").unlink()
        return whole[: int(len(whole) * int(kind.split("-")[1]) / 100)]
    if kind == "tiff16":
        import tifffile

        buffer = io.BytesIO()
        tifffile.imwrite(buffer, np.zeros((16, 16), dtype=np.uint16))
        return buffer.getvalue()
    if kind in ("png", "jpeg"):
        buffer = io.BytesIO()
        Image.fromarray(np.zeros((16, 16, 3), dtype=np.uint8)).save(buffer, format=kind.upper())
        return buffer.getvalue()
    return {"empty": b"", "random": np.random.default_rng(0).bytes(4096), "text": b"not a raw file\n" * 20}[kind]


@pytest.mark.parametrize("kind", ["empty", "random", "text", "truncated-1", "truncated-10", "truncated-50",
                                  "truncated-90", "truncated-99", "tiff16", "png", "jpeg"])
@pytest.mark.parametrize("suffix", [".dng", ".nef"])
def test_unconvertible_file(kind, suffix, tmp_path, capsys):
    path = tmp_path / f"capture{suffix}"
    path.write_bytes(_content(kind, tmp_path))
    out = tmp_path / "out"
    assert_clean_failure(capsys, ["convert", str(path), "--out", str(out), "--no-progress"], (path.name,),
                         watched=tmp_path)


def test_paths_that_are_not_raw_files(tmp_path, capsys):
    folder = tmp_path / "folder.dng"
    folder.mkdir()
    out = tmp_path / "out"
    for path in (folder, tmp_path / "missing.dng"):
        assert_clean_failure(capsys, ["convert", str(path), "--out", str(out), "--no-progress"], (path.name,),
                             watched=tmp_path)
    good = _simulated_dng(tmp_path / "good.dng")
    blocker = tmp_path / "out_is_a_file"
    blocker.write_text("")
    assert_clean_failure(capsys, ["convert", str(good), "--out", str(blocker), "--no-progress"], (blocker.name,),
                         watched=tmp_path)
