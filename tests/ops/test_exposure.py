"""exposure / exposure_gain / exposure_logit (plain torch: the camera folds the gain into the CFA responses)."""

import pytest
import torch

from warpsense.camera import Camera
from warpsense.config import load_config
from warpsense.ops.exposure import exposure, exposure_gain, exposure_logit


@pytest.mark.parametrize("gain", [0.3, 1.0, 2.0, 3.0, 3.9])
def test_feature_logit_inverts_the_gain(gain):
    assert float(exposure_gain(torch.tensor(exposure_logit(gain), dtype=torch.float64))) == pytest.approx(gain)


def test_module_a_config_logit_gives_the_camera_that_gain():
    camera = Camera.from_config(load_config("camvid_codesign", [f"exposure.gain_logit={exposure_logit(2.0)}"]))
    assert camera.learned().exposure_gain == pytest.approx(2.0, rel=1e-6)


@pytest.mark.parametrize("gain", [0.25, 4.0, 5.0, -1.0])
def test_exception_gain_outside_the_range(gain):
    with pytest.raises(ValueError, match="outside the exposure stage's range"):
        exposure_logit(gain)


def test_gradcheck():
    image = torch.rand(2, 3, 4, 5, dtype=torch.float64, requires_grad=True)
    logit = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(exposure, (image, logit))
