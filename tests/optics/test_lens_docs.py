"""docs/guide/camera.md's lens file format: its key table is the reader's (warpsense/optics/lens.py), its Noll table
is `ZERNIKE_NAMES`', and its worked example loads, renders, and gives what the page says of it."""

import json
import re
from pathlib import Path

import pytest
import torch

from warpsense.cli import main
from warpsense.optics.lens import OPTIONAL_KEYS, REQUIRED_KEYS, Lens, read_lens_spec
from warpsense.optics.report import nyquist_samples
from warpsense.optics.zernike import ZERNIKE_NAMES

PAGE = (Path(__file__).resolve().parents[2] / "docs" / "guide" / "camera.md").read_text()
FORMAT = PAGE.split("### The lens file", 1)[1].split("### A lens of your own", 1)[0]
EXAMPLE = PAGE.split("### A lens of your own", 1)[1].split("\n## ", 1)[0]


def test_the_key_table_names_every_key_the_reader_takes_and_no_other():
    keys = re.findall(r"^\| `(\w+)` \|", FORMAT, flags=re.MULTILINE)
    assert sorted(keys) == sorted([*REQUIRED_KEYS, *OPTIONAL_KEYS])
    for key, (_, default) in OPTIONAL_KEYS.items():  # the optional ones say so, with their default where it is fixed
        [row] = [line for line in FORMAT.splitlines() if line.startswith(f"| `{key}` |")]
        assert "optional" in row, key
        if isinstance(default, (int, float)) and key != "aspect_ratio":
            assert f"({default:g})" in row, key
    assert "optional" not in "".join(line for line in FORMAT.splitlines()
                                     if any(line.startswith(f"| `{key}` |") for key in REQUIRED_KEYS))


def test_the_noll_table_is_the_packages_naming():
    rows = re.findall(r"^\| (\d+(?:, \d+)?) \| ([^|]+?) \| (\d+(?:, \d+)?) \| ([^|]+?) \|$", FORMAT, flags=re.MULTILINE)
    named = {}
    for left, left_name, right, right_name in rows:
        for indices, name in ((left, left_name), (right, right_name)):
            for index in indices.split(", "):
                named[int(index)] = name
    assert sorted(named) == list(range(1, 14))
    for index, name in named.items():
        words = ZERNIKE_NAMES[index].replace("vertical ", "").replace("oblique ", "").split()
        assert all(word in name for word in words), (index, name, ZERNIKE_NAMES[index])


@pytest.fixture(scope="module")
def example(tmp_path_factory) -> Path:
    [block] = re.findall(r"```json\n(.*?)```", EXAMPLE, flags=re.DOTALL)
    path = tmp_path_factory.mktemp("lens") / "dashcam_60deg.json"  # the name the page saves it under
    path.write_text(block)
    return path


def test_the_worked_example_loads_and_is_what_the_page_says(example):
    spec = read_lens_spec(example)
    assert json.loads(example.read_text())["name"] == spec.name == "dashcam_60deg"
    assert f"{spec.sensor_diagonal_mm:.2f} mm" in EXAMPLE  # 2 f tan(FOV / 2)
    lens = Lens(spec)
    at = {h: dict(zip(lens.noll, lens.field_coefficients(torch.tensor([h], dtype=torch.float64))[0].tolist()))
          for h in (0.0, 1.0)}
    assert f"the defocus is {at[1.0][4]:.2f} waves rms" in EXAMPLE
    assert f"astigmatism {at[1.0][6]:.2f} and the coma {at[1.0][8]:.2f}" in EXAMPLE
    assert f"on the axis {at[0.0][4]:.2f} of defocus and {at[0.0][11]:.2f} of spherical" in EXAMPLE
    assert f"the blue image is {-100 * spec.lateral_color[2]:.2f}% smaller" in EXAMPLE
    assert f"the red {100 * spec.lateral_color[0]:.2f}%\nlarger" in EXAMPLE
    # the pixel integration: the bluest channel's Nyquist rate, above the default and below the file's oversampling
    needs = nyquist_samples(spec)
    assert f"needs {needs:.1f} samples per pixel" in EXAMPLE and OPTIONAL_KEYS["oversampling"][1] < needs
    assert spec.oversampling >= needs
    psf = lens.psf_grid()
    assert psf.shape == (3, 5, 7, 11, 11)
    torch.testing.assert_close(psf.sum(dim=(-2, -1)), torch.ones(3, 5, 7, dtype=psf.dtype))
    corner, centre = psf[1, 0, 0], psf[1, 2, 3]
    assert corner.max() < centre.max()  # the aberrations grow with the field: a wider PSF at the corner


def test_warpsense_lens_on_the_example_prints_what_the_page_reads_from_it(example, capsys):
    assert main(["lens", str(example)]) == 0
    out = capsys.readouterr().out
    sizes = {tolerance: int(re.search(rf"kernel size for <= {tolerance} outside at every node: (\d+)", out)[1])
             for tolerance in ("0.01", "0.001")}
    assert f"({sizes['0.01']} and {sizes['0.001']} for this lens)" in EXAMPLE
    assert "(exact)" in out  # oversampling 7 resolves the bluest channel
