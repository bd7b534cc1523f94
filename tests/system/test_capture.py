"""How a real RAW capture enters the model (`SensingModel.sense_capture`, warpsense/system/model.py): its exposure
scaled to half the camera's training level, clipped, times a photon budget's digital gain, through the fixed ISP."""

import pytest
import torch

from warpsense.config import load_config
from warpsense.system import build_system
from warpsense.system.model import CAPTURE_MEAN_SHARE

BAYER = ["cfa.mode=fixed", "cfa.pattern=RGGB"]


def _capture(height=8, width=12):
    return torch.rand(height, width, generator=torch.Generator().manual_seed(0)) * 0.1 + 0.01


@torch.no_grad()
def test_a_capture_enters_at_half_the_cameras_training_level():
    model = build_system(load_config(None, BAYER), 3).eval()
    mosaic = _capture()
    sensed = model.sense_capture(mosaic)
    level = model.camera.raw_mean()  # the normalised scene mean times the exposure gain
    assert CAPTURE_MEAN_SHARE == 0.5 and level == pytest.approx(0.25, rel=1e-5)  # no optics: a street frame's mean
    assert sensed.shape == (1, 1, 8, 12)
    assert float(sensed.mean()) == pytest.approx(0.5 * level, rel=1e-5)
    torch.testing.assert_close(sensed[0, 0] / sensed[0, 0, 0, 0], mosaic / mosaic[0, 0])  # a gain, nothing else
    bright = mosaic.clone()
    bright[0, 0] = 100.0  # a highlight: clipped at the white level after the scaling
    assert float(model.sense_capture(bright).max()) == 1.0


@torch.no_grad()
def test_a_photon_budget_gains_the_capture_and_the_isp_demosaics_it():
    """A photon budget has no exposure gain (the exposure is in electrons): the capture, in ADC units as the
    camera's ADC gives them, is clipped and gained into the network's range."""
    budget = build_system(load_config(None, [*BAYER, "photons.enabled=true", "photons.digital_gain=3.0",
                                             "noise.enabled=false", "exposure.enabled=false"]), 3).eval()
    mosaic = _capture()
    mosaic[0, 0] = 2.0
    torch.testing.assert_close(budget.sense_capture(mosaic)[0, 0], mosaic.clamp(0, 1) * 3.0)
    plain = build_system(load_config(None, BAYER), 3).eval()
    isp = build_system(load_config(None, [*BAYER, "isp.enabled=true"]), 3).eval()
    sensed = isp.sense_capture(mosaic)
    assert sensed.shape == (1, 3, 8, 12)
    torch.testing.assert_close(sensed, isp.isp(plain.sense_capture(mosaic)))
