"""Every op of one training step of the presets' recipe on CUDA (batch 16 at 352 x 480, joint phase, eager) whose
output holds >= 2M elements, with its input and output shapes, dtypes and strides and the autograd node running it
(views left out): where the step's copies and casts come from (docs/benchmarks.md, the training step)."""
import sys
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from step_profile import recipe_step  # noqa: E402

VIEWS = ("view", "permute", "slice", "as_strided", "empty", "select", "unsqueeze", "expand", "transpose", "detach",
         "alias", "squeeze")
"""Ops that make no copy (a name containing one of these), left out of the log; and aten.t."""

model, step, images, labels = recipe_step()
for i in range(3):
    step(model, images, labels, i, joint=True)
torch.cuda.synchronize()
class Log(TorchDispatchMode):
    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        name = str(func)
        if any(view in name for view in VIEWS) or name.startswith("aten.t."):
            return out
        o = out[0] if isinstance(out, (tuple, list)) and out else out
        if isinstance(o, torch.Tensor) and o.numel() >= 2_000_000:
            node = torch._C._current_autograd_node()
            ins = [(tuple(a.shape), str(a.dtype)[6:], a.stride()) for a in args if isinstance(a, torch.Tensor)]
            print(f"{name:34s} out {tuple(o.shape)} {str(o.dtype)[6:]} {o.stride()} node={node.name() if node else '-'} ins={ins}")
        return out
with Log():
    step(model, images, labels, 3, joint=True)
torch.cuda.synchronize()
