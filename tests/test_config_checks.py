"""Configurations and arguments that cannot work are refused at once, naming the field."""

import dataclasses

import pytest
import torch

from ebjepa_tutorial.course.presets import PRESETS
from ebjepa_tutorial.models.video import VideoJEPA
from ebjepa_tutorial.training.image import ImageJEPAConfig
from ebjepa_tutorial.training.video import VIDEO_CONFIGS, VideoJEPAConfig
from research.refit import RefitConfig


@pytest.mark.parametrize("config, change, message", [
    (ImageJEPAConfig, {"steps": 100}, "warmup_steps must be an int in 0..steps-1 = 99, got 200"),
    (VideoJEPAConfig, {"unroll": "teacher"}, "unroll must be one of \\['autoregressive', "),
    (RefitConfig, {"hidden": 0}, "RefitConfig.hidden must be an int >= 1"),
])
def test_a_config_that_cannot_work_names_its_field(config, change, message):
    with pytest.raises(ValueError, match=message):
        config(**change)


def test_every_preset_is_a_valid_config():
    # building scale.PRESETS ran every __post_init__; the replaced copies must pass too
    for notebook in ("01", "02"):
        for preset in PRESETS[notebook].values():
            dataclasses.replace(preset.long_config)
    assert all(PRESETS[n] for n in PRESETS)


def test_float_frames_in_0_255_are_refused_and_uint8_accepted():
    model = VideoJEPA(VIDEO_CONFIGS["ci"].model)
    frames = torch.randint(0, 256, (1, 2, 1, 64, 64), dtype=torch.uint8)
    with pytest.raises(ValueError, match=r"uint8 or float in 0\.\.1"):
        model.encode(frames.float())
    assert torch.equal(model.encode(frames), model.encode(frames.float() / 255))
