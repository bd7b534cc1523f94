"""A UNet decoder's bilinear x2 upsampling fused with its skip concatenation, on channels-last planes, as Warp kernels.

    out[b, Y, X, c] = up(x)[b, Y, X, c]          for c < C1
                    = skip[b, Y, X, c - C1]     for C1 <= c < C1 + C2

``up`` is torch's bilinear resize with ``align_corners=False`` to exactly twice the size (`torch.nn.functional.
interpolate`, docs/references.md): along each axis output 2i takes 3/4 of input i and 1/4 of input i - 1, output
2i + 1 takes 3/4 of i and 1/4 of i + 1, neighbours clamped at the edges. Layouts: x [B, h, w, C1], skip and the
gradient of the skipped channels [B, 2h, 2w, C2], out [B, 2h, 2w, C1 + C2]; channels innermost, so neighbouring
threads touch neighbouring addresses. Arithmetic is float32 for bfloat16 and float32 arrays, float64 for float64.

The backward gathers: each input sums the 4 x 4 outputs it reached, with the same weights, in a fixed order. One
writer per element, no atomics: deterministic (torch's CUDA backward of the resize scatters with atomic adds).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

RUN = 8  # pixels of one row per thread: the launch's index arithmetic (64-bit divisions) paid once for RUN elements


@wp.func
def widen(value: wp.bfloat16):
    """The arithmetic type of an element: float32 for bfloat16."""
    return wp.float32(value)


@wp.func
def widen(value: wp.float32):  # noqa: F811  - Warp overloads functions by argument type
    return value


@wp.func
def widen(value: wp.float64):  # noqa: F811
    return value


@wp.func
def quarter(near: Any, far: Any):
    """3/4 of ``near`` and 1/4 of ``far``."""
    return near + (far - near) * type(near)(0.25)


@wp.func
def neighbour(i: int, odd: bool, size: int):
    """The input that output 2i (``odd`` false) or 2i + 1 (true) takes its quarter from, clamped at the edges."""
    if odd:
        return wp.min(i + 1, size - 1)
    return wp.max(i - 1, 0)


@wp.kernel
def upsample_concat_forward(
    x: wp.array4d(dtype=Any),
    skip: wp.array4d(dtype=Any),
    out: wp.array4d(dtype=Any),
):
    """Thread (b * 2h + Y, column group, c): channel c of RUN neighbouring output pixels. Neighbouring threads hold
    neighbouring channels, so each load and store of a warp is one contiguous run."""
    row, group, c = wp.tid()
    height = out.shape[1]
    b = row / height
    y = row % height
    channels = x.shape[3]
    if c >= channels:
        for m in range(RUN):
            col = group * RUN + m
            if col < out.shape[2]:
                out[b, y, col, c] = skip[b, y, col, c - channels]
        return
    i = y / 2
    ni = neighbour(i, y % 2 == 1, x.shape[1])
    for m in range(RUN):
        col = group * RUN + m
        if col < out.shape[2]:
            j = col / 2
            nj = neighbour(j, col % 2 == 1, x.shape[2])
            near = quarter(widen(x[b, i, j, c]), widen(x[b, i, nj, c]))
            far = quarter(widen(x[b, ni, j, c]), widen(x[b, ni, nj, c]))
            out[b, y, col, c] = out.dtype(quarter(near, far))


@wp.func
def weight(offset: int, i: int, size: int, one: Any):
    """Weight of output 2i - 1 + ``offset`` (``offset`` 0..3) on input i of ``size``, in the type of ``one``. The
    first and last outputs' clamped neighbour is their own input, which so takes all of them."""
    if offset == 0:
        if i > 0:
            return type(one)(0.25)
        return type(one)(0.0)
    if offset == 3:
        if i < size - 1:
            return type(one)(0.25)
        return type(one)(0.0)
    if (offset == 1 and i == 0) or (offset == 2 and i == size - 1):
        return one
    return type(one)(0.75)


@wp.kernel
def upsample_concat_backward(
    grad_out: wp.array4d(dtype=Any),
    grad_x: wp.array4d(dtype=Any),
):
    """Thread (b * h + i, column group, c): channel c of RUN neighbouring inputs (i, j) of image b, each gathering
    outputs 2i - 1 .. 2i + 2 by 2j - 1 .. 2j + 2; the rows and their weights found once."""
    row, group, c = wp.tid()
    height = grad_x.shape[1]
    width = grad_x.shape[2]
    b = row / height
    i = row % height
    one = widen(grad_x.dtype(1.0))
    ys = wp.vector(length=4, dtype=int)
    wy = wp.vector(length=4, dtype=type(one))
    for o in range(4):
        ys[o] = wp.min(wp.max(2 * i - 1 + o, 0), 2 * height - 1)
        wy[o] = weight(o, i, height, one)
    for m in range(RUN):
        j = group * RUN + m
        if j < width:
            total = type(one)(0.0)
            for ox in range(4):
                x = wp.min(wp.max(2 * j - 1 + ox, 0), 2 * width - 1)
                column = type(one)(0.0)
                for oy in range(4):
                    column += wy[oy] * widen(grad_out[b, ys[oy], x, c])
                total += weight(ox, j, width, one) * column
            grad_x[b, i, j, c] = grad_x.dtype(total)


for _float in (wp.bfloat16, wp.float32, wp.float64):
    _planes = wp.array4d(dtype=_float)
    wp.overload(upsample_concat_forward, [_planes, _planes, _planes])
    wp.overload(upsample_concat_backward, [_planes, _planes])
