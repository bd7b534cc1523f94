"""Spatially varying PSF convolution (paper eq. 2) as Warp kernels.

    out(p) = sum_d x(clamp(p - d)) * PSF_{clamp(p - d)}(d),   PSF_q = sum_n w_n(q) PSF_n

Each source pixel q spreads its light with the PSF interpolated at q (bilinear over a grid of node PSFs whose nodes
sit at the centres of a Gy x Gx tiling, clamped beyond the outer centres), so a point source renders as its PSF
centred on it, unflipped, and energy is conserved away from the borders. Borders are clamp-to-edge.

Layouts: image/out [B*C, H, W]; psf [C, Gy*Gx, K, K] (node (iy, ix) at iy*Gx + ix; Warp arrays have at most 4
dimensions) with K odd, tap (i, j) at offset d = (i - K//2, j - K//2).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def node_lower(pixel: int, size: int, nodes: int):
    """Index of the lower of the two grid nodes bracketing pixel ``pixel`` along an axis."""
    if nodes == 1:
        return 0
    position = (float(pixel) + 0.5) / float(size) * float(nodes) - 0.5
    position = wp.clamp(position, 0.0, float(nodes - 1))
    return wp.min(int(wp.floor(position)), nodes - 2)


@wp.func
def node_fraction(pixel: int, size: int, nodes: int, lower: int, like: Any):
    """Weight of the upper node (1 - weight of the lower), in the float type of ``like``."""
    if nodes == 1:
        return type(like)(0.0)
    position = (type(like)(pixel) + type(like)(0.5)) / type(like)(size) * type(like)(nodes) - type(like)(0.5)
    position = wp.clamp(position, type(like)(0.0), type(like)(nodes - 1))
    return position - type(like)(lower)


@wp.func
def interpolated_tap(
    psf: wp.array4d(dtype=Any), c: int, iy: int, ix: int, fy: Any, fx: Any, grid_y: int, grid_x: int, i: int, j: int
):
    one = type(fy)(1.0)
    node = iy * grid_x + ix
    value = (one - fy) * (one - fx) * psf[c, node, i, j]
    if grid_x > 1:
        value += (one - fy) * fx * psf[c, node + 1, i, j]
    if grid_y > 1:
        value += fy * (one - fx) * psf[c, node + grid_x, i, j]
        if grid_x > 1:
            value += fy * fx * psf[c, node + grid_x + 1, i, j]
    return value


@wp.kernel
def psf_forward(
    image: wp.array3d(dtype=Any), psf: wp.array4d(dtype=Any), grid_x: int, out: wp.array3d(dtype=Any)
):
    bc, y, x = wp.tid()
    channels = psf.shape[0]
    grid_y = psf.shape[1] / grid_x
    size = psf.shape[2]
    radius = size / 2
    height = image.shape[1]
    width = image.shape[2]
    c = bc % channels
    acc = image.dtype(0.0)
    for i in range(size):
        qy = wp.clamp(y - (i - radius), 0, height - 1)
        iy = node_lower(qy, height, grid_y)
        fy = node_fraction(qy, height, grid_y, iy, acc)
        for j in range(size):
            qx = wp.clamp(x - (j - radius), 0, width - 1)
            ix = node_lower(qx, width, grid_x)
            fx = node_fraction(qx, width, grid_x, ix, acc)
            acc += image[bc, qy, qx] * interpolated_tap(psf, c, iy, ix, fy, fx, grid_y, grid_x, i, j)
    out[bc, y, x] = acc


@wp.kernel
def psf_backward_image(
    grad_out: wp.array3d(dtype=Any), psf: wp.array4d(dtype=Any), grid_x: int, grad_image: wp.array3d(dtype=Any)
):
    """Gather per source pixel q: the outputs it reached through every virtual position that clamps to q."""
    bc, y, x = wp.tid()
    channels = psf.shape[0]
    grid_y = psf.shape[1] / grid_x
    size = psf.shape[2]
    radius = size / 2
    height = grad_out.shape[1]
    width = grad_out.shape[2]
    c = bc % channels
    acc = grad_out.dtype(0.0)
    iy = node_lower(y, height, grid_y)
    fy = node_fraction(y, height, grid_y, iy, acc)
    ix = node_lower(x, width, grid_x)
    fx = node_fraction(x, width, grid_x, ix, acc)
    y_first = y
    y_last = y
    x_first = x
    x_last = x
    if y == 0:
        y_first = -radius
    if y == height - 1:
        y_last = height - 1 + radius
    if x == 0:
        x_first = -radius
    if x == width - 1:
        x_last = width - 1 + radius
    if y_first == y_last and x_first == x_last:
        # interior pixel: one virtual position, a plain correlation with its own PSF
        for i in range(size):
            py = y + i - radius
            if py >= 0 and py < height:
                for j in range(size):
                    px = x + j - radius
                    if px >= 0 and px < width:
                        acc += interpolated_tap(psf, c, iy, ix, fy, fx, grid_y, grid_x, i, j) * grad_out[bc, py, px]
    else:
        for i in range(size):
            for j in range(size):
                tap = interpolated_tap(psf, c, iy, ix, fy, fx, grid_y, grid_x, i, j)
                reached = grad_out.dtype(0.0)
                for vy in range(y_first, y_last + 1):
                    py = vy + i - radius
                    if py >= 0 and py < height:
                        for vx in range(x_first, x_last + 1):
                            px = vx + j - radius
                            if px >= 0 and px < width:
                                reached += grad_out[bc, py, px]
                acc += tap * reached
    grad_image[bc, y, x] = acc


@wp.kernel
def psf_backward_psf(
    image: wp.array3d(dtype=Any),
    grad_out: wp.array3d(dtype=Any),
    rows: wp.array2d(dtype=wp.int32),
    cols: wp.array2d(dtype=wp.int32),
    grid_y: int,
    grid_x: int,
    size: int,
    channels: int,
    row_chunk: int,
    partials: wp.array2d(dtype=Any),
):
    """dL/dPSF_n(d) = sum_{b, p} g(b, p) x(b, q) w_n(q), q = clamp(p - d), reduced without atomics.

    Thread (tap, lane): tap enumerates (c, node, i, j); lane enumerates (b, chunk of output rows). Only output
    pixels whose source lies in node n's support (rows[n_y], cols[n_x], conservative) are visited. Each thread
    writes its partial sum to partials[tap, lane]; the caller sums over lanes.
    """
    tap, lane = wp.tid()
    height = image.shape[1]
    width = image.shape[2]
    radius = size / 2
    j = tap % size
    i = (tap / size) % size
    node_x = (tap / (size * size)) % grid_x
    node_y = (tap / (size * size * grid_x)) % grid_y
    c = tap / (size * size * grid_x * grid_y)
    chunks = (height + row_chunk - 1) / row_chunk
    b = lane / chunks
    chunk = lane % chunks
    bc = b * channels + c
    dy = i - radius
    dx = j - radius
    # output rows/cols whose clamped source can fall in the node's support
    y_first = rows[node_y, 0] + dy
    y_last = rows[node_y, 1] + dy
    if rows[node_y, 0] == 0:
        y_first = 0
    if rows[node_y, 1] == height - 1:
        y_last = height - 1
    x_first = cols[node_x, 0] + dx
    x_last = cols[node_x, 1] + dx
    if cols[node_x, 0] == 0:
        x_first = 0
    if cols[node_x, 1] == width - 1:
        x_last = width - 1
    y_first = wp.max(wp.max(y_first, 0), chunk * row_chunk)
    y_last = wp.min(wp.min(y_last, height - 1), chunk * row_chunk + row_chunk - 1)
    x_first = wp.max(x_first, 0)
    x_last = wp.min(x_last, width - 1)
    acc = image.dtype(0.0)
    one = image.dtype(1.0)
    for py in range(y_first, y_last + 1):
        qy = wp.clamp(py - dy, 0, height - 1)
        iy = node_lower(qy, height, grid_y)
        fy = node_fraction(qy, height, grid_y, iy, acc)
        weight_y = image.dtype(0.0)
        if node_y == iy:
            weight_y = one - fy
        elif node_y == iy + 1:
            weight_y = fy
        if weight_y != image.dtype(0.0):
            row_acc = image.dtype(0.0)
            for px in range(x_first, x_last + 1):
                qx = wp.clamp(px - dx, 0, width - 1)
                ix = node_lower(qx, width, grid_x)
                fx = node_fraction(qx, width, grid_x, ix, acc)
                weight_x = image.dtype(0.0)
                if node_x == ix:
                    weight_x = one - fx
                elif node_x == ix + 1:
                    weight_x = fx
                row_acc += weight_x * image[bc, qy, qx] * grad_out[bc, py, px]
            acc += weight_y * row_acc
    partials[tap, lane] = acc


for _float in (wp.float32, wp.float64):
    _planes = wp.array3d(dtype=_float)
    _grid = wp.array4d(dtype=_float)
    wp.overload(psf_forward, [_planes, _grid, int, _planes])
    wp.overload(psf_backward_image, [_planes, _grid, int, _planes])
    _bounds = wp.array2d(dtype=wp.int32)
    wp.overload(psf_backward_psf, [_planes, _planes, _bounds, _bounds, int, int, int, int, int, wp.array2d(dtype=_float)])
