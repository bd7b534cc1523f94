"""The stage protocol: every camera stage builds itself from its config section and reports its learned state."""

import dataclasses

import pytest
import torch

from warpsense.camera import Camera
from warpsense.camera.camera import STAGES
from warpsense.camera.stage import Stage
from warpsense.config import Config, load_config

ALL_STAGES = ["optics.enabled=true", "optics.learnable=true", "noise.learnable=true"]
PHOTON_STAGES = ["optics.enabled=true", "optics.learnable=true", "optics.normalize_mean=0.0", "photons.enabled=true",
                 "noise.enabled=false", "exposure.enabled=false", "photons.gain_learnable=true",
                 "photons.analog_gain=2.0"]


def test_every_stage_names_a_config_section_with_an_enabled_key():
    sections = {field.name for field in dataclasses.fields(Config)}
    for name, stage in STAGES.items():
        assert issubclass(stage, Stage), name
        assert stage.config_section in sections, name
        assert "enabled" in {field.name for field in dataclasses.fields(getattr(Config(), stage.config_section))}


@pytest.mark.parametrize("overrides, left_out", [(ALL_STAGES, {"photons"}),
                                                 (PHOTON_STAGES, {"noise", "exposure"})])
def test_stage_from_its_section_equals_the_cameras_stage(overrides, left_out):
    config = load_config("camvid_codesign", overrides)
    camera = Camera.from_config(config)
    # all enabled but those the photon budget replaces, in data-path order
    assert [name for name, _ in camera.stages()] == [name for name in STAGES if name not in left_out]
    for name, stage in camera.stages():
        alone = STAGES[name].from_config(getattr(config, STAGES[name].config_section))
        assert type(alone) is type(stage)
        for (key, value), (_, expected) in zip(alone.state_dict().items(), stage.state_dict().items()):
            assert key.endswith("seed_counter") or torch.equal(value, expected), (name, key)


def test_camera_iterates_only_enabled_stages_and_sections_decide():
    config = load_config(None, ["noise.enabled=false", "optics.enabled=false"])
    camera = Camera.from_config(config)
    assert [name for name, _ in camera.stages()] == ["exposure", "cfa", "quantizer"]
    assert [name for name, _ in Camera().stages()] == []


def test_summary_is_the_union_of_stage_summaries_and_reports_learned_values():
    config = load_config("camvid_codesign", ALL_STAGES + ["cfa.pattern=BGGR", "noise.shot=0.02", "noise.read=0.004"])
    camera = Camera.from_config(config)
    summary = camera.summary()
    assert set(summary) == {"zernike_waves", "exposure_gain", "cfa_layout", "cfa_choice", "cfa_phi", "temperature",
                            "noise_shot", "noise_read"}
    assert summary["cfa_layout"] == "BGGR"
    assert summary["exposure_gain"] == pytest.approx(float(camera.exposure.gain().detach()))
    assert summary["noise_shot"] == pytest.approx(0.02) and summary["noise_read"] == pytest.approx(0.004)
    assert torch.tensor(summary["cfa_phi"]).shape == (2, 2, 3)
    assert summary["zernike_waves"] == camera.optics.lens.coefficients().tolist()
    with torch.no_grad():  # learned state moves: the summary follows it
        camera.exposure.gain_logit.add_(1.0)
    assert camera.summary()["exposure_gain"] > summary["exposure_gain"]
    fixed_lens = Camera.from_config(load_config(None, ["optics.enabled=true"]))
    assert "zernike_waves" not in fixed_lens.summary()  # a fixed lens learns nothing


def test_learnable_parameters_are_those_the_config_made_learnable_whatever_the_phase():
    camera = Camera.from_config(load_config(None, ["exposure.learnable=true", "noise.learnable=false"]))
    names = {name for name, p in camera.named_parameters() if any(p is q for q in camera.learnable_parameters())}
    assert names == {"exposure.gain_logit", "cfa.logits"}
    for p in camera.parameters():
        p.requires_grad_(False)  # a warm-up phase freezes them; they stay the learnable ones
    assert len(camera.learnable_parameters()) == 2
