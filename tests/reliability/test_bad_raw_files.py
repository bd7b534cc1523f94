"""Raw captures that cannot be converted: empty, random, text, truncated at several points, other formats named
.dng, folders and missing paths. `warpsense convert` reports each in one line naming it, exits non-zero and writes
no output for it (issue 14, item 4); the batch case lives in tests/data/test_raw.py. `warpsense predict` refuses a
capture input that is not one (a .safetensors that `warpsense convert` did not write, a folder) the same way."""

import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from safetensors.torch import save_file

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


CHECKPOINT = Path(__file__).resolve().parents[2] / "checkpoints" / "camvid_fixed_isp.safetensors"


def _capture_bytes(tmp_path, metadata, mosaic=None):
    path = tmp_path / "whole.safetensors"
    save_file({"mosaic": torch.zeros(1, 8, 8) if mosaic is None else mosaic}, str(path), metadata=metadata)
    whole = path.read_bytes()
    path.unlink()
    return whole


@pytest.mark.parametrize("kind,reason", [
    ("empty", "header too small"), ("text", "header"), ("truncated", "Error while deserializing"),
    ("no metadata", "no 'warpsense' metadata"), ("metadata not JSON", "not JSON"),
    ("no cfa_pattern", "names no cfa_pattern"), ("checkpoint", "no 'mosaic' tensor"),
    ("cfa_pattern not text", "names no cfa_pattern"), ("mosaic [H, W]", "its 'mosaic' is float32 [8, 8], expected"),
    ("mosaic of 3 planes", "float32 [3, 8, 8]"), ("mosaic float16", "float16 [1, 8, 8]"),
    ("mosaic int32", "int32 [1, 8, 8]"), ("mosaic 1 x 1", "float32 [1, 1, 1]"), ("mosaic empty", "[1, 0, 0]"),
    ("mosaic NaN", "holds NaN or infinite values")])
def test_predict_refuses_a_safetensors_that_is_no_capture(kind, reason, tmp_path, capsys):
    """Each was a traceback (safetensors' "header too small", a TypeError for no metadata or a cfa_pattern that is
    no text, torch errors for a float16, integer or empty mosaic), an error naming no file ("not enough values to
    unpack" for a mosaic of other dimensions), or an image written without complaint (a mosaic of NaN, of 3
    planes) or a bare "mosaic" (a checkpoint given as the capture)."""
    metadata = {"warpsense": json.dumps({"cfa_pattern": "RGGB"})}
    capture = _capture_bytes(tmp_path, metadata)
    mosaics = {"mosaic [H, W]": torch.zeros(8, 8), "mosaic of 3 planes": torch.zeros(3, 8, 8),
               "mosaic float16": torch.zeros(1, 8, 8, dtype=torch.float16),
               "mosaic int32": torch.zeros(1, 8, 8, dtype=torch.int32), "mosaic 1 x 1": torch.zeros(1, 1, 1),
               "mosaic empty": torch.zeros(1, 0, 0), "mosaic NaN": torch.full((1, 8, 8), float("nan"))}
    content = {"empty": b"", "text": b"hello\n", "truncated": capture[: len(capture) // 2],
               "no metadata": _capture_bytes(tmp_path, None),
               "metadata not JSON": _capture_bytes(tmp_path, {"warpsense": "{oops"}),
               "no cfa_pattern": _capture_bytes(tmp_path, {"warpsense": "{}"}),
               "checkpoint": CHECKPOINT.read_bytes(),
               "cfa_pattern not text": _capture_bytes(tmp_path, {"warpsense": json.dumps({"cfa_pattern": 5})}),
               **{name: _capture_bytes(tmp_path, metadata, mosaic) for name, mosaic in mosaics.items()}}[kind]
    path = tmp_path / "capture.safetensors"
    path.write_bytes(content)
    out = tmp_path / "p.png"
    assert_clean_failure(capsys, ["predict", str(CHECKPOINT), str(path), "--out", str(out), "--device", "cpu"],
                         (f"{path}: not a raw capture written by `warpsense convert`", reason), watched=tmp_path)


def test_predict_names_a_capture_whose_cfa_is_no_bayer_layout(tmp_path, capsys):
    """`warpsense simulate` writes RCCB and monochrome captures, which predict cannot read: the error was
    "layout RCCB cannot be cropped into RGGB", naming no file."""
    path = tmp_path / "rccb.safetensors"
    path.write_bytes(_capture_bytes(tmp_path, {"warpsense": json.dumps({"cfa_pattern": "RCCB"})}))
    out = tmp_path / "p.png"
    assert_clean_failure(capsys, ["predict", str(CHECKPOINT), str(path), "--out", str(out), "--device", "cpu"],
                         (f"{path}: the capture's CFA 'RCCB' is not a Bayer layout",), watched=tmp_path)


def test_predict_names_a_capture_too_small_for_the_phase_crop(tmp_path, capsys):
    """A 2 x 2 BGGR capture cropped by (1, 1) into the model's RGGB keeps no whole tile: the network got an empty
    image and the command ended in a torch traceback."""
    path = tmp_path / "tiny.safetensors"
    path.write_bytes(_capture_bytes(tmp_path, {"warpsense": json.dumps({"cfa_pattern": "BGGR"})},
                                    torch.rand(1, 2, 2)))
    out = tmp_path / "p.png"
    assert_clean_failure(capsys, ["predict", str(CHECKPOINT), str(path), "--out", str(out), "--device", "cpu"],
                         (f"{path}: its 2x2 mosaic holds no whole RGGB tile",), watched=tmp_path)


def test_predict_names_a_folder_given_as_the_capture(tmp_path, capsys):
    """A folder was reported as "no such file"."""
    folder = tmp_path / "captures"
    folder.mkdir()
    out = tmp_path / "p.png"
    assert_clean_failure(capsys, ["predict", str(CHECKPOINT), str(folder), "--out", str(out), "--device", "cpu"],
                         (f"{folder}: is a folder, expected a raw file",), watched=tmp_path)


def test_predict_points_an_srgb_image_to_simulate(tmp_path, capsys):
    """An sRGB PNG given as the capture was "LibRaw cannot read it" alone; it is a scene, which `warpsense
    simulate` turns into a capture."""
    import numpy as np
    from PIL import Image

    scene = tmp_path / "street.png"
    Image.fromarray(np.zeros((8, 8, 3), dtype=np.uint8)).save(scene)
    out = tmp_path / "p.png"
    assert_clean_failure(capsys, ["predict", str(CHECKPOINT), str(scene), "--out", str(out), "--device", "cpu"],
                         (f"{scene}: LibRaw cannot read it", "warpsense simulate"), watched=tmp_path)
