"""Run a tool with one of the network's fused ops replaced by its torch form, for an A/B in one call:

    python tools/device/ab.py SWITCH tools/bench_train_bound.py ARGS...

SWITCH: "fused" (as shipped), "torch-norm" (batch norm + ReLU through torch), "torch-gate" (the squeeze-and-
excitation gate and residual through torch), "torch-joins" (the decoder's upsampling and concatenation through
torch), "torch-all" (the three).
"""

import runpy
import sys

import warpsense.models.dsunet as dsunet


def torch_norm(norm, x):
    return dsunet.F.relu(norm(x))


def torch_gate(x, gate, residual=None):
    return x * gate if residual is None else residual + x * gate


SWITCHES = {
    "fused": [],
    "torch-norm": [("norm_relu", torch_norm)],
    "torch-gate": [("channel_gate", torch_gate)],
    "torch-joins": [("FUSED_JOINS", False)],
}
SWITCHES["torch-all"] = SWITCHES["torch-norm"] + SWITCHES["torch-gate"] + SWITCHES["torch-joins"]

if __name__ == "__main__":
    switch, script = sys.argv[1], sys.argv[2]
    if switch not in SWITCHES:
        raise SystemExit(f"unknown switch {switch!r}; valid: {', '.join(SWITCHES)}")
    for name, value in SWITCHES[switch]:
        if name == "FUSED_JOINS":
            dsunet.DSUNet._up_cat = lambda self, x, skip: dsunet.torch.cat([self._up(x, skip), skip], dim=1)
        else:
            setattr(dsunet, name, value)
    sys.argv = [script] + sys.argv[3:]
    runpy.run_path(script, run_name="__main__")
