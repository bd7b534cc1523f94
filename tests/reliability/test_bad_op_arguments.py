"""Op arguments: wrong types, dtypes, shapes, empty or zero-size grids and out-of-range levels are refused before
any kernel launch with a TypeError or ValueError naming the op (issue 14, items 3 and 12). What the ops accept by
policy (any finite PSF values, non-finite values propagating) is documented in `warpsense.ops.arguments`."""

import pytest
import torch

from warpsense.ops import (
    cfa_mosaic,
    exposure,
    exposure_gain,
    poisson_gaussian,
    poisson_gaussian_exact,
    psf_conv,
    quantize_ste,
)
from warpsense.ops.sensor import sensor_capture

IMAGE = torch.rand(1, 3, 8, 8)
PSF = torch.full((3, 2, 2, 3, 3), 1 / 9)
RAW = torch.rand(1, 1, 8, 8)
PHI = torch.rand(2, 2, 3)
LOGIT = torch.tensor(0.0)

CASES = {
    "psf_conv": [
        lambda: psf_conv(IMAGE.numpy(), PSF), lambda: psf_conv(IMAGE, PSF.tolist()), lambda: psf_conv(IMAGE.int(), PSF),
        lambda: psf_conv(IMAGE, PSF.int()), lambda: psf_conv(IMAGE[0], PSF), lambda: psf_conv(IMAGE, PSF[0]),
        lambda: psf_conv(IMAGE[:, :2], PSF), lambda: psf_conv(IMAGE, PSF[:, :0, :0]),
        lambda: psf_conv(IMAGE, PSF[:, :0]),
        lambda: psf_conv(IMAGE, PSF[:, :, :0]), lambda: psf_conv(IMAGE, PSF[..., :2, :2]),
        lambda: psf_conv(IMAGE, PSF[..., :1]), lambda: psf_conv(IMAGE, PSF, "magic"),
        lambda: psf_conv(IMAGE[:, :, :0], PSF), lambda: psf_conv(IMAGE[:0], PSF), lambda: psf_conv(IMAGE, PSF, "fft"),
        lambda: psf_conv(None, PSF), lambda: psf_conv(IMAGE, PSF[:, :, :, :0, :0]),
    ],
    "cfa_mosaic": [
        lambda: cfa_mosaic(IMAGE.numpy(), PHI), lambda: cfa_mosaic(IMAGE, PHI.tolist()),
        lambda: cfa_mosaic(IMAGE[:, :2], PHI), lambda: cfa_mosaic(IMAGE, PHI[0]),
        lambda: cfa_mosaic(IMAGE, torch.rand(2, 2, 4)), lambda: cfa_mosaic(IMAGE, torch.rand(2, 3, 3)),
        lambda: cfa_mosaic(IMAGE.int(), PHI), lambda: cfa_mosaic(IMAGE[0], PHI), lambda: cfa_mosaic(IMAGE[:0], PHI),
        lambda: cfa_mosaic(IMAGE, torch.rand(0, 0, 3)),
    ],
    "poisson_gaussian": [
        lambda: poisson_gaussian(RAW.numpy(), 0.01, 0.002, 0), lambda: poisson_gaussian(RAW, -0.01, 0.002, 0),
        lambda: poisson_gaussian(RAW, float("nan"), 0.002, 0), lambda: poisson_gaussian(RAW, 0.01, -0.002, 0),
        lambda: poisson_gaussian(RAW, 0.01, float("inf"), 0), lambda: poisson_gaussian(RAW, "a", 0.002, 0),
        lambda: poisson_gaussian(RAW, True, 0.002, 0), lambda: poisson_gaussian(RAW, 0.01, 0.002, 1.5),
        lambda: poisson_gaussian(RAW, torch.tensor([0.1, 0.2]), 0.002, 0),
        lambda: poisson_gaussian(RAW, torch.tensor(1), 0.002, 0), lambda: poisson_gaussian(RAW.int(), 0.01, 0.002, 0),
        lambda: poisson_gaussian(RAW[:0], 0.01, 0.002, 0), lambda: poisson_gaussian(RAW, 0.01, 0.002, torch.zeros(3)),
        lambda: poisson_gaussian(RAW, 0.01, 0.002, torch.zeros(1, dtype=torch.float32)),
        lambda: poisson_gaussian(RAW, 0.01, 0.002, None),
    ],
    "poisson_gaussian_exact": [
        lambda: poisson_gaussian_exact(RAW, -0.01, 0.002, 0),
        lambda: poisson_gaussian_exact(RAW.tolist(), 0.01, 0.0, 0),
        lambda: poisson_gaussian_exact(RAW, 0.01, float("nan"), 0), lambda: poisson_gaussian_exact(RAW[:0], 0.01, 0, 0),
    ],
    "quantize_ste": [
        lambda: quantize_ste(RAW, True), lambda: quantize_ste(RAW, 10.0), lambda: quantize_ste(RAW, 0),
        lambda: quantize_ste(RAW, 64), lambda: quantize_ste(RAW, 10, float("nan")),
        lambda: quantize_ste(RAW, 10, float("inf")), lambda: quantize_ste(RAW, 10, 1e-46),
        lambda: quantize_ste(RAW, 10, 1e39), lambda: quantize_ste(RAW, 10, -1.0), lambda: quantize_ste(RAW, 10, 0.0),
        lambda: quantize_ste(RAW, 10, True), lambda: quantize_ste(RAW, 10, "1"),
        lambda: quantize_ste(RAW, 10, 1.0, "x"),
        lambda: quantize_ste(RAW.numpy(), 10), lambda: quantize_ste(RAW.int(), 10), lambda: quantize_ste(RAW[:0], 10),
    ],
    "exposure": [
        lambda: exposure(IMAGE.numpy(), LOGIT), lambda: exposure(IMAGE, 0.0), lambda: exposure(IMAGE, torch.zeros(2)),
        lambda: exposure(IMAGE.int(), LOGIT), lambda: exposure(IMAGE[0], LOGIT), lambda: exposure(IMAGE, LOGIT.int()),
    ],
    "exposure_gain": [lambda: exposure_gain([0.0]), lambda: exposure_gain(0.0), lambda: exposure_gain(LOGIT.long())],
    "sensor_capture": [
        lambda: sensor_capture(IMAGE.numpy(), PHI), lambda: sensor_capture(IMAGE, PHI.tolist()),
        lambda: sensor_capture(IMAGE, PHI, -0.1, 0.0), lambda: sensor_capture(IMAGE, PHI, 0.1, float("nan")),
        lambda: sensor_capture(IMAGE, PHI, 0.1, None), lambda: sensor_capture(IMAGE, PHI, bits=True),
        lambda: sensor_capture(IMAGE, PHI, bits=0), lambda: sensor_capture(IMAGE.int(), PHI),
        lambda: sensor_capture(IMAGE[:, :1], PHI), lambda: sensor_capture(IMAGE, PHI[0]),
        lambda: sensor_capture(IMAGE[:0], PHI), lambda: sensor_capture(IMAGE, PHI, bits=10, white_level=0.0),
    ],
}


@pytest.mark.parametrize("op, case", [pytest.param(op, case, id=f"{op}-{index}")
                                      for op, cases in CASES.items() for index, case in enumerate(cases)])
def test_bad_argument_is_a_one_line_error_naming_the_op(op, case):
    with pytest.raises((TypeError, ValueError)) as raised:
        case()
    message = str(raised.value)
    assert message.startswith(f"{op}:") and "\n" not in message, message
