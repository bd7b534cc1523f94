"""Every op of one training step of the presets' recipe on CUDA (batch 16 at 352 x 480, joint phase, eager) whose
output holds >= 2M elements, with its input and output shapes, dtypes and strides and the autograd node running it
(views left out): where the step's copies and casts come from (docs/benchmarks.md, the training step)."""
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from warpsense.camera.camera import set_finite_check
from warpsense.config import load_config
from warpsense.data.photometric import RadianceJitter
from warpsense.system.build import build_system
from warpsense.train.engine import _optimizer
from warpsense.train.step import TrainingStep

torch.manual_seed(0)
config = load_config("camvid_codesign", [])
model = build_system(config, 11).cuda().train()
set_finite_check(model, False)
optimizer = _optimizer(config, model, torch.device("cuda"))
step = TrainingStep(config.loss, optimizer, model.camera.learnable_parameters(), 1000, True,
                    config.train.camera_grad_clip, "off", False, radiance_jitter=RadianceJitter.from_config(config.data))
images = torch.randint(0, 256, (16, 3, 352, 480), dtype=torch.uint8, device="cuda")
labels = torch.randint(0, 11, (16, 352, 480), device="cuda")
for i in range(3):
    step(model, images, labels, i, joint=True)
torch.cuda.synchronize()
class Log(TorchDispatchMode):
    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        name = str(func)
        if "view" in name or "permute" in name or "slice" in name or "as_strided" in name or "empty" in name or "select" in name or "unsqueeze" in name or "expand" in name or "transpose" in name or name.startswith("aten.t.") or "detach" in name or "alias" in name or "_unsafe_view" in name or "squeeze" in name:
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
