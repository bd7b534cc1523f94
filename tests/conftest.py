from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def cuda_available() -> bool:
    return torch.cuda.is_available()


def pytest_collection_modifyitems(config, items):
    if cuda_available():
        return
    skip = pytest.mark.skip(reason="no CUDA GPU present")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)


def device_params():
    """CPU always; CUDA as a cuda-marked variant."""
    return [pytest.param("cpu", id="cpu"), pytest.param("cuda", id="cuda", marks=pytest.mark.cuda)]


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA} (tests expect ../shared/data beside the repo)")
    return SHARED_DATA


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    yield


def assert_matches_reference(operation, reference, inputs, grad_output, check_forward=True):
    """The op's output and its gradients w.r.t. every input that requires grad (for ``grad_output``) equal the
    reference implementation's."""
    wanted = [x for x in inputs if x.requires_grad]
    mine_out, theirs_out = operation(*inputs), reference(*inputs)
    if check_forward:
        torch.testing.assert_close(mine_out, theirs_out)
    mine = torch.autograd.grad(mine_out, wanted, grad_output)
    theirs = torch.autograd.grad(theirs_out, wanted, grad_output)
    for a, b in zip(mine, theirs):
        torch.testing.assert_close(a.reshape(b.shape), b)
