"""Lens files: every key with a wrong type, required keys missing, absurd sizes (bounded before any allocation),
and files that are not JSON objects. `warpsense lens FILE` fails with one line naming the file."""

import json

import pytest

from tests.reliability.conftest import assert_clean_failure
from warpsense.optics.lens import OPTIONAL_KEYS, REQUIRED_KEYS
from warpsense.resources import CONFIG_DIR

GOOD = json.loads((CONFIG_DIR / "lenses" / "phone_68deg.json").read_text())
WRONG = {str: 5, float: "x", int: "x", list: "x", dict: [1, 2]}


def _mutations():
    for key, kind in {**REQUIRED_KEYS, **{k: v[0] for k, v in OPTIONAL_KEYS.items()}}.items():
        yield f"type-{key}", {**GOOD, key: WRONG[kind]}, key
    for key in REQUIRED_KEYS:
        yield f"missing-{key}", {k: v for k, v in GOOD.items() if k != key}, key
    ranges = {
        "psf_kernel_size": [0, 4, 1001, 10**9], "psf_grid": [[0, 5], [5], [1000, 1000], [5, True]],
        "oversampling": [0, 2, 999], "pupil_samples": [4, 100000], "f_number": [0, -1.9],
        "focal_length_mm": [0, -4.2], "pixel_pitch_um": [0], "diagonal_fov_deg": [0, 180, 400],
        "wavelengths_um": [[0.55, 0.46], [-0.6, 0.55, 0.46], ["a", 0.55, 0.46]], "aspect_ratio": [0, -1],
        "reference_wavelength_um": [-0.5, 0], "axial_color_waves": [[1, 2], [1e9, 0, 0]],
        "lateral_color": [[0, 0], [1e9, 0, 0]], "max_energy_outside": [0, 0.9],
        "learnable_bound_waves": [-1, 1e9], "zernike_waves": [{"99": {"constant": 0.1}}, {"x": {"constant": 0.1}},
                                                             {"4": {"cubic": 0.1}}, {"4": {"constant": 1e9}},
                                                             {"4": [0.1]}],
    }
    for key, values in ranges.items():
        for index, value in enumerate(values):
            yield f"range-{key}-{index}", {**GOOD, key: value}, key
    yield "unknown-key", {**GOOD, "focal_lenght_mm": 4.2}, "focal_lenght_mm"


@pytest.mark.parametrize("data, key", [pytest.param(d, k, id=i) for i, d, k in _mutations()])
def test_invalid_lens_values(data, key, tmp_path, capsys):
    path = tmp_path / "lens.json"
    path.write_text(json.dumps(data))
    assert_clean_failure(capsys, ["lens", str(path)], (str(path), key))


@pytest.mark.parametrize("content", [
    b"", b"[]", b"null", b"42", b"\"lens\"", b"{", b"\xff\xfe{}", b"[" * 100000 + b"]" * 100000,
    b'{"f_number": ' + b"9" * 5000 + b"}", b"{\"name\": NaN}",
], ids=["empty", "list", "null", "number", "string", "truncated", "not-utf8", "deep", "5000-digits", "nan"])
def test_unreadable_lens_files(content, tmp_path, capsys):
    path = tmp_path / "lens.json"
    path.write_bytes(content)
    assert_clean_failure(capsys, ["lens", str(path)], (str(path),))


def test_lens_paths_that_are_not_files(tmp_path, capsys):
    folder = tmp_path / "folder.json"
    folder.mkdir()
    assert_clean_failure(capsys, ["lens", str(folder)], (str(folder),))
    assert_clean_failure(capsys, ["lens", str(tmp_path / "missing.json")], ("missing.json",))
    assert_clean_failure(capsys, ["lens", "no_such_lens"], ("no_such_lens",))
