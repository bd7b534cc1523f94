"""A UNet decoder's bilinear x2 upsampling, written straight into its skip concatenation, as Warp kernels.

    out[b, Y, X, c] = up(x)[b, Y, X, c]          for c < C1   (these kernels)
                    = skip[b, Y, X, c - C1]     for C1 <= c < C1 + C2   (copied by the op, `warpsense.ops.upsample`)

``up`` is torch's bilinear resize with ``align_corners=False`` to exactly twice the size (`torch.nn.functional.
interpolate`, docs/references.md): along each axis output 2i takes 3/4 of input i and 1/4 of input i - 1, output
2i + 1 takes 3/4 of i and 1/4 of i + 1, neighbours clamped at the edges. Layouts: x and its gradient [B, h, w, C1],
out and its gradient [B, 2h, 2w, C1 + C2]; channels innermost, so neighbouring threads touch neighbouring
addresses. Arithmetic is float32 for bfloat16 and float32 arrays, float64 for float64.

The backward gathers: each input sums the 4 x 4 outputs it reached, with the same weights, in a fixed order. One
writer per element, no atomics: deterministic (torch's CUDA backward of the resize scatters with atomic adds).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

RUN = 8  # pixels of one row per thread (even): loads shared between neighbours, index arithmetic paid once


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


@wp.func
def run_of(t: int, channels: int, groups: int, height: int):
    """Thread t of a one-dimensional launch over (image, row, run of RUN pixels, channel), channels fastest ->
    (image, row, the run's first column, channel)."""
    c = t % channels
    rest = t / channels
    row = rest / groups
    return row / height, row % height, (rest % groups) * RUN, c


@wp.kernel
def upsample_concat_forward(
    x: wp.array4d(dtype=Any),
    groups: int,
    out: wp.array4d(dtype=Any),
):
    """The upsampled channels c < C1 of ``out`` (the caller copies the skipped ones: a strided copy, which torch's
    kernels do at full bandwidth; in this kernel the two kinds of thread shared warps and diverged). Thread
    ((b * 2h + Y) * groups + group) * C1 + c: channel c of the RUN output pixels of row Y from column group * RUN
    on. Neighbouring threads hold neighbouring channels, so each load and store of a warp is one contiguous run;
    a one-dimensional launch, so that the index arithmetic is 32-bit. The RUN / 2 + 2 input columns the run reads
    are interpolated along y once each."""
    b, y, start, c = run_of(wp.tid(), x.shape[3], groups, out.shape[1])
    i = y / 2
    ni = neighbour(i, y % 2 == 1, x.shape[1])
    first = start / 2 - 1  # input column of v[0]
    last = x.shape[2] - 1
    v = wp.vector(length=wp.static(RUN // 2 + 2), dtype=type(widen(x.dtype(0.0))))
    for k in range(wp.static(RUN // 2 + 2)):
        column = wp.min(wp.max(first + k, 0), last)
        v[k] = quarter(widen(x[b, i, column, c]), widen(x[b, ni, column, c]))
    for q in range(wp.static(RUN // 2)):
        col = start + 2 * q
        if col < out.shape[2]:
            out[b, y, col, c] = out.dtype(quarter(v[q + 1], v[q]))
            out[b, y, col + 1, c] = out.dtype(quarter(v[q + 1], v[q + 2]))


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
    groups: int,
    grad_x: wp.array4d(dtype=Any),
):
    """Thread ((b * h + i) * groups + group) * C1 + c: channel c of the RUN inputs of row i from column group * RUN
    on (the forward's layout). Each of the 2 RUN + 2 output columns they reach is summed over its 4 output rows
    once; each input then takes 4 of those sums."""
    height = grad_x.shape[1]
    width = grad_x.shape[2]
    b, i, start, c = run_of(wp.tid(), grad_x.shape[3], groups, height)
    one = widen(grad_x.dtype(1.0))
    ys = wp.vector(length=4, dtype=int)
    wy = wp.vector(length=4, dtype=type(one))
    for o in range(4):
        ys[o] = wp.min(wp.max(2 * i - 1 + o, 0), 2 * height - 1)
        wy[o] = weight(o, i, height, one)
    sums = wp.vector(length=wp.static(2 * RUN + 2), dtype=type(one))  # output columns 2 start - 1 on
    for k in range(wp.static(2 * RUN + 2)):
        column = wp.min(wp.max(2 * start - 1 + k, 0), 2 * width - 1)
        for o in range(4):
            sums[k] = sums[k] + wy[o] * widen(grad_out[b, ys[o], column, c])
    for m in range(RUN):
        j = start + m
        if j < width:
            value = type(one)(0.0)
            for o in range(4):
                value += weight(o, j, width, one) * sums[2 * m + o]
            grad_x[b, i, j, c] = grad_x.dtype(value)


for _float in (wp.bfloat16, wp.float32, wp.float64):
    _planes = wp.array4d(dtype=_float)
    wp.overload(upsample_concat_forward, [_planes, int, _planes])
    wp.overload(upsample_concat_backward, [_planes, int, _planes])
