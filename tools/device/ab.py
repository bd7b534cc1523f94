"""Run a tool with some of the fused Warp ops of the network or the loss in their torch form, for an A/B in one call:

    python tools/device/ab.py SWITCH SCRIPT ARGS...
    python tools/device/ab.py torch-norm warpsense/__main__.py bench --suite train --device cuda --json OUT.json

SWITCH: "fused" (as shipped); "torch-joins", "torch-norm", "torch-gate" (that network op through torch: the
decoder's upsampling and concatenation, batch norm + ReLU, the squeeze-and-excitation gate and residual);
"torch-softmax", "torch-lovasz", "torch-smoothness" (that loss op's torch form: torch's softmax and
cross-entropy, the terms' plain-torch references); "torch-network" (the three network ops), "torch-loss" (the three
loss ops), "torch-all" (all six); "fused-single-joins" (as shipped, but a single image in eager eval mode joins with
the fused op too, as it once did). The script (any Python file, `warpsense/__main__.py` for a `warpsense` command)
runs inside the switches the benchmarks' baseline uses (`warpsense.models.dsunet.NETWORK_OPS`,
`warpsense.train.losses.LOSS_OPS`).
"""

import contextlib
import runpy
import sys

from warpsense.models import dsunet
from warpsense.models.dsunet import NETWORK_OPS
from warpsense.train.losses import LOSS_OPS


@contextlib.contextmanager
def fused_single_joins():
    """DSUNet's joins fused for one image in eager eval mode too: its capture test answers yes throughout."""
    capturing = dsunet._capturing
    dsunet._capturing = lambda x: True
    try:
        yield
    finally:
        dsunet._capturing = capturing


SWITCHES = {"fused": {}, "torch-network": {NETWORK_OPS: ()}, "torch-loss": {LOSS_OPS: ()},
            "torch-all": {NETWORK_OPS: (), LOSS_OPS: ()}, "fused-single-joins": {},
            **{f"torch-{name}": {ops: (name,)} for ops in (NETWORK_OPS, LOSS_OPS) for name in ops.names}}

if __name__ == "__main__":
    switch, script = sys.argv[1], sys.argv[2]
    if switch not in SWITCHES:
        raise SystemExit(f"unknown switch {switch!r}; valid: {', '.join(SWITCHES)}")
    sys.argv = [script] + sys.argv[3:]
    with contextlib.ExitStack() as stack:
        for ops, names in SWITCHES[switch].items():
            stack.enter_context(ops.torch_ops(*names))
        if switch == "fused-single-joins":
            stack.enter_context(fused_single_joins())
        runpy.run_path(script, run_name="__main__")
