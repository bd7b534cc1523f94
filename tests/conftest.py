import os
from pathlib import Path

from warpsense.cli import _cpu_thread_defaults

# Before torch loads its OpenMP runtime: its idle threads sleep instead of spinning, as in every command's process.
# The suite runs study pools, CLI subprocesses and sampler threads beside the test process, and with libgomp's
# spinning default a test after them ran 40x slower than alone (3 s -> 130 s for a 3-epoch resume test).
_cpu_thread_defaults()
# pytest-xdist's workers share the cores: torch's threads (and those of the commands a test starts) a share each
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _WORKERS > 1:
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, len(os.sched_getaffinity(0)) // _WORKERS)))

import pytest  # noqa: E402
import torch  # noqa: E402

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def cuda_available() -> bool:
    return torch.cuda.is_available()


def pytest_collection_modifyitems(config, items):
    # the longest tests first, so that the workers run the others beside them instead of after them
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
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


@pytest.fixture
def ctrl_c():
    """Python's Ctrl-C handler (KeyboardInterrupt) for a test that sends itself SIGINT: a suite started in the
    background (`python -m pytest &`, nohup) inherits SIGINT ignored, and the signal would then do nothing."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


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
