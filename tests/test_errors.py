import pytest
import torch

from warpsense.data.datasets import DatasetError
from warpsense.errors import first_line, worker_message


def test_first_line_of_a_long_message_or_the_type_of_an_empty_one():
    assert first_line(RuntimeError("\n  CUDA error: operation not permitted\nstack trace ...")) == \
        "CUDA error: operation not permitted"
    assert first_line(ValueError("")) == "ValueError"
    assert first_line(KeyError()) == "KeyError"


class _BadFile(torch.utils.data.Dataset):
    def __len__(self):
        return 1

    def __getitem__(self, index):
        raise DatasetError("/data/val/cut.png: unreadable image (image file is truncated)")


def test_worker_message_is_the_workers_own_message_without_its_traceback():
    """torch raises a DataLoader worker's error again with the worker's traceback as its message: `warpsense train`
    with data.num_workers > 0 printed some twenty lines for a bad image."""
    with pytest.raises(DatasetError) as caught:
        next(iter(torch.utils.data.DataLoader(_BadFile(), num_workers=1)))
    assert "Traceback" in str(caught.value)  # torch's wrapping, which the message must not keep
    assert worker_message(str(caught.value)) == "/data/val/cut.png: unreadable image (image file is truncated)"
    assert worker_message("a: b\nc: d") == "a: b\nc: d"  # any other message as it is
