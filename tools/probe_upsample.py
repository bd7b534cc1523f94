"""TEMPORARY probe: where the fused join's forward spends its time (full-resolution join, bf16, H100)."""
import torch
import warp as wp

from warpsense.bench.timing import time_function
from warpsense.kernels import upsample as K
from warpsense.ops._warp import launch
from warpsense.ops.upsample import upsample_concat

RUN = K.RUN


@wp.kernel(module="unique", enable_backward=False)
def x_part(x: wp.array4d(dtype=wp.bfloat16), groups: int, channels_out: int, out: wp.array4d(dtype=wp.bfloat16)):
    t = wp.tid()
    channels = x.shape[3]
    c = t % channels
    rest = t / channels
    group = rest % groups
    row = rest / groups
    height = out.shape[1]
    b = row / height
    y = row % height
    start = group * RUN
    i = y / 2
    ni = K.neighbour(i, y % 2 == 1, x.shape[1])
    first = start / 2 - 1
    last = x.shape[2] - 1
    v = wp.vector(length=wp.static(RUN // 2 + 2), dtype=wp.float32)
    for k in range(wp.static(RUN // 2 + 2)):
        column = wp.min(wp.max(first + k, 0), last)
        v[k] = K.quarter(wp.float32(x[b, i, column, c]), wp.float32(x[b, ni, column, c]))
    for q in range(wp.static(RUN // 2)):
        col = start + 2 * q
        out[b, y, col, c] = wp.bfloat16(K.quarter(v[q + 1], v[q]))
        out[b, y, col + 1, c] = wp.bfloat16(K.quarter(v[q + 1], v[q + 2]))


@wp.kernel(module="unique", enable_backward=False)
def copy_part(skip: wp.array4d(dtype=wp.bfloat16), groups: int, offset: int, out: wp.array4d(dtype=wp.bfloat16)):
    t = wp.tid()
    channels = skip.shape[3]
    c = t % channels
    rest = t / channels
    group = rest % groups
    row = rest / groups
    height = out.shape[1]
    b = row / height
    y = row % height
    start = group * RUN
    for m in range(RUN):
        out[b, y, start + m, c + offset] = skip[b, y, start + m, c]


@wp.kernel(module="unique", enable_backward=False)
def plain_copy(skip: wp.array(dtype=wp.bfloat16), out: wp.array(dtype=wp.bfloat16)):
    t = wp.tid()
    out[t] = skip[t]


def main():
    device = torch.device("cuda", 0)
    b, h, w = 16, 352, 480
    x = torch.randn(b, h // 2, w // 2, 48, device=device, dtype=torch.bfloat16)
    skip = torch.randn(b, h, w, 24, device=device, dtype=torch.bfloat16)
    out = torch.empty(b, h, w, 72, device=device, dtype=torch.bfloat16)
    groups = w // RUN
    xs, ss = x.permute(0, 3, 1, 2), skip.permute(0, 3, 1, 2)
    cases = {
        "op forward (no_grad)": lambda: upsample_concat(xs, ss),
        "x part only": lambda: launch(x_part, b * h * groups * 48, [x, groups, 72, out], device),
        "skip part only": lambda: launch(copy_part, b * h * groups * 24, [skip, groups, 48, out], device),
        "warp flat copy of skip": lambda: launch(plain_copy, skip.numel(), [skip.view(-1), out.view(-1)[:skip.numel()]], device),
        "torch out[..., 48:].copy_(skip)": lambda: out[..., 48:].copy_(skip),
        "torch contiguous copy of out": lambda: out.clone(),
    }
    for name, function in cases.items():
        with torch.no_grad():
            print(f"{name:>36s} {time_function(function, device, 30)['median_ms']:.3f} ms", flush=True)
    graph_ms = {}
    for name in ("op forward (no_grad)", "x part only", "skip part only"):
        from warpsense.bench.timing import time_cuda_graph
        with torch.no_grad():
            graph_ms[name] = time_cuda_graph(cases[name], 30)["median_ms"]
        print(f"{name + ' graph':>36s} {graph_ms[name]:.3f} ms", flush=True)


if __name__ == "__main__":
    main()
