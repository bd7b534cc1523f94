"""WeightEMA: the average against a hand-written recurrence, the in-place swap, and resuming."""

import pytest
import torch
from torch import nn

from warpsense.train.ema import WeightEMA


def _model():
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(3, 2), nn.BatchNorm1d(2))


def _stepped():
    """A model and its average (decay 0.9) after one update that followed a change of the weights."""
    model = _model()
    ema = WeightEMA(model, 0.9)
    with torch.no_grad():
        model[0].weight.add_(1.0)
    ema.update()
    return model, ema


def test_update_follows_the_warmed_up_recurrence():
    model = _model()
    ema = WeightEMA(model, 0.5)
    weight = model[0].weight
    expected = weight.detach().clone()
    for n in range(1, 6):
        with torch.no_grad():
            weight.add_(float(n))
        ema.update()
        decay = min(0.5, (1 + n) / (10 + n))
        expected = decay * expected + (1 - decay) * weight.detach()
        torch.testing.assert_close(ema.shadow[ema.names.index("0.weight")], expected)
    assert "1.running_mean" in ema.names and "1.num_batches_tracked" not in ema.names  # floats only


def test_applied_swaps_in_place_and_restores():
    model, ema = _stepped()
    storage = model[0].weight.data_ptr()
    own = model[0].weight.detach().clone()
    with ema.applied():
        assert model[0].weight.data_ptr() == storage  # a captured CUDA graph keeps reading the same memory
        torch.testing.assert_close(model[0].weight.detach(), ema.shadow[ema.names.index("0.weight")])
    torch.testing.assert_close(model[0].weight.detach(), own)


def test_resume_takes_the_checkpoints_average_and_training_weights():
    model, ema = _stepped()
    live = ema.live_tensors()
    with ema.applied():
        averaged = {f"model.{k}": v.clone() for k, v in model.state_dict().items()}
    fresh = _model()
    fresh.load_state_dict({k[len("model."):]: v for k, v in averaged.items()})  # what `restore` does
    resumed = WeightEMA(fresh, 0.9)
    resumed.resume({**averaged, **live})
    torch.testing.assert_close(fresh[0].weight.detach(), model[0].weight.detach())
    torch.testing.assert_close(resumed.shadow[0], ema.shadow[0])
    assert resumed.updates.item() == 1


def test_exception_decay_outside_the_open_interval():
    with pytest.raises(ValueError, match="ema_decay"):
        WeightEMA(_model(), 1.0)
