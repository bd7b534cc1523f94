"""Run a tool with some of the network's fused Warp ops in their torch form, for an A/B in one call:

    python tools/device/ab.py SWITCH tools/bench_train_bound.py ARGS...

SWITCH: "fused" (as shipped), "torch-joins", "torch-norm" or "torch-gate" (that op through torch: the decoder's
upsampling and concatenation, batch norm + ReLU, the squeeze-and-excitation gate and residual), "torch-all" (all
three). The script runs inside `warpsense.models.dsunet.torch_ops`, the switch the benchmarks' baseline uses.
"""

import runpy
import sys

from warpsense.models.dsunet import FUSED_OPS, torch_ops

SWITCHES = {"fused": None, "torch-all": (), **{f"torch-{name}": (name,) for name in FUSED_OPS}}

if __name__ == "__main__":
    switch, script = sys.argv[1], sys.argv[2]
    if switch not in SWITCHES:
        raise SystemExit(f"unknown switch {switch!r}; valid: {', '.join(SWITCHES)}")
    sys.argv = [script] + sys.argv[3:]
    if SWITCHES[switch] is None:
        runpy.run_path(script, run_name="__main__")
    else:
        with torch_ops(*SWITCHES[switch]):
            runpy.run_path(script, run_name="__main__")
