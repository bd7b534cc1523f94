"""Spatially varying PSF convolution (paper eq. 2) as Warp kernels.

    out(p) = sum_d x(clamp(p - d)) * PSF_{clamp(p - d)}(d),   PSF_q = sum_n w_n(q) PSF_n

Each source pixel q spreads its light with the PSF interpolated at q, bilinear between the four nodes of the grid
cell that holds q, so a point source renders as its PSF centred on it, unflipped, and energy is conserved away from
the borders. Borders are clamp-to-edge.

Where the nodes sit is not decided here: per-axis tables give each pixel's cell and its fraction towards the upper
node (``row_cell``/``row_frac``, ``col_cell``/``col_frac``), and ``row_bounds``/``col_bounds`` give the first pixel of
each cell (the last entry is the image size). The op layer builds them (`warpsense.ops.psf`).

Layouts (Warp arrays have at most 4 dimensions):
    image, out: [B*C, H, W]
    cells: [C, cells_y * cells_x, K, K] of 4-vectors (PSF of the cell's nodes (0,0), (0,1), (1,0), (1,1)), so a tap
        reads its four node values in one vector load; cell (cy, cx) at index cy * cells_x + cx.
    tap (i, j) sits at offset d = (i - K//2, j - K//2), K odd.

Every kernel is a gather with one writer per output element: no atomics, deterministic.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def bilinear(corners: Any, fy: Any, fx: Any):
    """Value at fractions (fy, fx) inside a cell from its corner values (00, 01, 10, 11)."""
    top = corners[0] + fx * (corners[1] - corners[0])
    bottom = corners[2] + fx * (corners[3] - corners[2])
    return top + fy * (bottom - top)


@wp.kernel
def psf_forward(
    image: wp.array3d(dtype=Any),
    cells: wp.array4d(dtype=Any),
    cells_x: int,
    row_cell: wp.array(dtype=wp.int32),
    row_frac: wp.array(dtype=Any),
    col_cell: wp.array(dtype=wp.int32),
    col_frac: wp.array(dtype=Any),
    out: wp.array3d(dtype=Any),
):
    """One thread per output pixel: sum over taps of the source pixel times its interpolated PSF tap."""
    bc, y, x = wp.tid()
    channels = cells.shape[0]
    size = cells.shape[2]
    radius = size / 2
    height = image.shape[1]
    width = image.shape[2]
    c = bc % channels
    acc = image.dtype(0.0)
    for i in range(size):
        qy = wp.clamp(y - i + radius, 0, height - 1)
        fy = row_frac[qy]
        row_base = row_cell[qy] * cells_x
        for j in range(size):
            qx = wp.clamp(x - j + radius, 0, width - 1)
            tap = bilinear(cells[c, row_base + col_cell[qx], i, j], fy, col_frac[qx])
            acc += image[bc, qy, qx] * tap
    out[bc, y, x] = acc


@wp.kernel
def psf_backward_image(
    grad_out: wp.array3d(dtype=Any),
    cells: wp.array4d(dtype=Any),
    cells_x: int,
    row_cell: wp.array(dtype=wp.int32),
    row_frac: wp.array(dtype=Any),
    col_cell: wp.array(dtype=wp.int32),
    col_frac: wp.array(dtype=Any),
    grad_image: wp.array3d(dtype=Any),
):
    """One thread per source pixel q: the outputs it reached, each through q's own PSF. A border pixel also
    collects what the virtual positions beyond the border (which clamp to it) reached."""
    bc, y, x = wp.tid()
    channels = cells.shape[0]
    size = cells.shape[2]
    radius = size / 2
    height = grad_out.shape[1]
    width = grad_out.shape[2]
    c = bc % channels
    cell = row_cell[y] * cells_x + col_cell[x]
    fy = row_frac[y]
    fx = col_frac[x]
    acc = grad_out.dtype(0.0)
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
        for i in range(size):
            py = y + i - radius
            if py >= 0 and py < height:
                for j in range(size):
                    px = x + j - radius
                    if px >= 0 and px < width:
                        acc += bilinear(cells[c, cell, i, j], fy, fx) * grad_out[bc, py, px]
    else:
        for i in range(size):
            for j in range(size):
                reached = grad_out.dtype(0.0)
                for vy in range(y_first, y_last + 1):
                    py = vy + i - radius
                    if py >= 0 and py < height:
                        for vx in range(x_first, x_last + 1):
                            px = vx + j - radius
                            if px >= 0 and px < width:
                                reached += grad_out[bc, py, px]
                acc += bilinear(cells[c, cell, i, j], fy, fx) * reached
    grad_image[bc, y, x] = acc


@wp.func
def reached_range(bounds: wp.array(dtype=wp.int32), cell: int, cells: int, offset: int, size: int):
    """Output coordinates [first, last) whose clamped source (coordinate - offset) lies in ``cell``."""
    first = bounds[cell] + offset
    last = bounds[cell + 1] + offset
    if cell == 0:
        first = 0
    if cell == cells - 1:
        last = size
    return wp.max(first, 0), wp.min(last, size)


@wp.kernel
def psf_backward_cells(
    image: wp.array3d(dtype=Any),
    grad_out: wp.array3d(dtype=Any),
    row_bounds: wp.array(dtype=wp.int32),
    row_frac: wp.array(dtype=Any),
    col_bounds: wp.array(dtype=wp.int32),
    col_frac: wp.array(dtype=Any),
    size: int,
    channels: int,
    cells_y: int,
    cells_x: int,
    row_chunks: int,
    partials: wp.array4d(dtype=Any),
):
    """dL/dcell_n(d) for the four corners of each cell: sum over outputs p whose source q = clamp(p - d) lies in the
    cell of g(p) x(q) times q's bilinear corner weights.

    Thread (tap, lane): tap enumerates (c, i, j); lane enumerates (b, cell, chunk of the cell's reached rows). The
    weights are separable, so each row keeps two sums (sum v and sum fx * v, v = g x) and folds them into the four
    corners with its fy. Each thread writes its own partials[lane, c, ., tap] (summed over batch and chunks by the
    caller): no atomics.
    """
    tap, lane = wp.tid()
    height = image.shape[1]
    width = image.shape[2]
    radius = size / 2
    j = tap % size
    i = (tap / size) % size
    c = tap / (size * size)
    chunk = lane % row_chunks
    cell = (lane / row_chunks) % (cells_y * cells_x)
    b = lane / (row_chunks * cells_y * cells_x)
    cy = cell / cells_x
    cx = cell % cells_x
    dy = i - radius
    dx = j - radius
    bc = b * channels + c
    y_first, y_end = reached_range(row_bounds, cy, cells_y, dy, height)
    x_first, x_end = reached_range(col_bounds, cx, cells_x, dx, width)
    rows = wp.max(y_end - y_first, 0)
    per_chunk = (rows + row_chunks - 1) / row_chunks
    y_start = y_first + chunk * per_chunk
    y_stop = wp.min(y_start + per_chunk, y_end)
    zero = image.dtype(0.0)
    one = image.dtype(1.0)
    s00 = zero
    s01 = zero
    s10 = zero
    s11 = zero
    for py in range(y_start, y_stop):
        qy = wp.clamp(py - dy, 0, height - 1)
        fy = row_frac[qy]
        total = zero
        upper = zero
        for px in range(x_first, x_end):
            qx = wp.clamp(px - dx, 0, width - 1)
            v = grad_out[bc, py, px] * image[bc, qy, qx]
            total += v
            upper += col_frac[qx] * v
        lower = total - upper
        s00 += (one - fy) * lower
        s01 += (one - fy) * upper
        s10 += fy * lower
        s11 += fy * upper
    partials[lane / (cells_y * cells_x * row_chunks) * row_chunks + chunk, c, cell, tap % (size * size)] = wp.vector(
        s00, s01, s10, s11
    )


for _float, _vec4 in ((wp.float32, wp.vec4f), (wp.float64, wp.vec4d)):
    _planes = wp.array3d(dtype=_float)
    _cells = wp.array4d(dtype=_vec4)
    _table = wp.array(dtype=_float)
    _index = wp.array(dtype=wp.int32)
    wp.overload(psf_forward, [_planes, _cells, int, _index, _table, _index, _table, _planes])
    wp.overload(psf_backward_image, [_planes, _cells, int, _index, _table, _index, _table, _planes])
    wp.overload(psf_backward_cells, [_planes, _planes, _index, _table, _index, _table, int, int, int, int, int,
                                     wp.array4d(dtype=_vec4)])
