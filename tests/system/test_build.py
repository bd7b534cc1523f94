"""Building the system from a config (warpsense/system/build.py)."""

import pytest

from warpsense.config import load_config
from warpsense.system import build_system


@pytest.mark.parametrize("num_classes", [0, -1, 11.0, True])
def test_exception_num_classes_must_be_a_positive_int(num_classes):
    """0 built a network whose head had no outputs (logits [B, 0, H, W]); 11.0 and -1 failed inside torch."""
    with pytest.raises(ValueError, match=f"^build_system: num_classes must be a positive int, got {num_classes!r}$"):
        build_system(load_config(None), num_classes)


def test_smoke_the_head_predicts_num_classes():
    model = build_system(load_config(None), 5)
    assert model.network.head.out_channels == 5
