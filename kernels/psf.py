"""Spatially varying PSF convolution (eq. 2 of the paper, docs/references.md) as Warp kernels.

    out(p) = sum_d x(clamp(p - d)) * PSF_{clamp(p - d)}(d),   PSF_q = sum_n w_n(q) PSF_n

Each source pixel q spreads its light with the PSF interpolated at q, bilinear between the four nodes of the grid
cell that holds q, so a point source renders as its PSF centred on it, unflipped, and energy is conserved away from
the borders. Borders are clamp-to-edge.

The kernels work on padded planes so that their inner loops carry no bounds checks and no clamps:
    source: the image replicate-padded by r = K // 2 on every side (plus `ROWS - 1` extra rows at the bottom),
        [B*C, H + 2r + ROWS - 1, W + 2r]; source pixel s is image pixel clamp(s - r).
    padded gradient: grad_out zero-padded by 2r on every side (plus `ROWS - 1` extra rows and `TAPS - 1` extra
        columns), so output p = s - 2r + (i, j) of source s under tap (i, j) sits at (s_y + i, s_x + j).
Per-axis tables over padded source coordinates give each source's cell and its fraction towards the upper node
(``row_cell``/``row_frac``, ``col_cell``/``col_frac``); ``row_bounds``/``col_bounds`` give the first padded source
of each cell (the last entry is the padded size). The op layer builds them (`warpsense.ops.psf`).

PSF layout: ``cells`` [C, cells_y * cells_x, K, K] of 4-vectors (PSF of the cell's nodes (0,0), (0,1), (1,0),
(1,1)), so a tap reads its four node values in one vector load; tap (i, j) sits at offset d = (i - r, j - r).

Why these kernels are fast: the forward and the image adjoint (`psf_kernels`, one pair per K, which they take as
a compile-time constant) give each thread ROWS outputs of one column in registers. For each tap column the thread
loads the K + ROWS - 1 values of its window once and runs all K tap rows from registers; where the window lies in
one grid cell, which holds for most threads, a tap is one warp-uniform vector load, interpolated along x once
for the ROWS outputs, and each output then costs two fused multiply-adds. Neighbouring threads hold neighbouring
columns, so every load is coalesced. The PSF adjoint slides TAPS taps along each source row: `psf_cells_staged`
with the gradient rows a block reads staged in shared memory, `psf_backward_cells` (PSFs too large to stage)
from global memory. Every kernel is a gather with one writer per output element: no atomics, deterministic.

The planes, tables and cells are contiguous (the op layer builds them) and are read by flat element offset
(`load`, `load_node`), so an inner loop's loads are an address and a constant; offsets are int32 (the op layer
refuses larger images). What bounds them, and how far they are from the GPU's arithmetic peak: docs/benchmarks.md,
PSF convolution.
"""

import functools
from typing import Any, NamedTuple

import warp as wp

wp.set_module_options({"enable_backward": False})

# Loads by flat element offset from a contiguous array's start. Warp's `array[i, j, k]` computes a 64-bit byte
# offset per axis and wraps negative indices per axis on every access: in the forward about half of the
# instructions (docs/benchmarks.md, PSF convolution). With offsets the compiler folds a constant step into the load
# (`at + i * size` with i and size constants) and keeps one running offset per loop. On CUDA a 4-vector of float32 is
# one 16-byte load (the op layer passes 16-byte-aligned cells).
_LOAD = "return a.data[i];"
_LOAD_VEC4F = """#if defined(__CUDA_ARCH__)
const float4 v = __ldg(reinterpret_cast<const float4*>(a.data) + i);
return wp::vec_t<4, wp::float32>(v.x, v.y, v.z, v.w);
#else
return a.data[i];
#endif
"""  # the closing newline: Warp appends the function's brace to the snippet's last line


@wp.func_native(_LOAD)
def load(a: wp.array3d(dtype=wp.float32), i: int) -> wp.float32: ...


@wp.func_native(_LOAD)
def load(a: wp.array3d(dtype=wp.float64), i: int) -> wp.float64: ...  # noqa: F811 (an overload)


@wp.func_native(_LOAD)
def load(a: wp.array(dtype=wp.float32), i: int) -> wp.float32: ...  # noqa: F811 (an overload)


@wp.func_native(_LOAD)
def load(a: wp.array(dtype=wp.float64), i: int) -> wp.float64: ...  # noqa: F811 (an overload)


@wp.func_native(_LOAD_VEC4F)
def load_node(a: wp.array4d(dtype=wp.vec4f), i: int) -> wp.vec4f: ...


@wp.func_native(_LOAD)
def load_node(a: wp.array4d(dtype=wp.vec4d), i: int) -> wp.vec4d: ...  # noqa: F811 (an overload)


FORWARD_BOUNDS = (128, 5)
"""CUDA launch bounds of the forward and image-adjoint kernels (maxThreadsPerBlock, minBlocksPerMultiprocessor): blocks
of 128 threads, five a multiprocessor, which caps a thread at ~100 registers (146 uncapped, three blocks): more warps
hide the loads' latency (docs/benchmarks.md, PSF convolution). The op layer launches blocks of the first."""

ROWS = 8  # output rows per thread in the forward and image-adjoint kernels
TAPS = 8  # PSF taps (consecutive j) per thread in the PSF-adjoint kernel (the fastest of 4, 8 and 16)


@wp.func
def along_x(corners: Any, fx: Any):
    """A cell's corner values (00, 01, 10, 11) interpolated along x: the values on its top and bottom edges."""
    return corners[0] + fx * (corners[1] - corners[0]), corners[2] + fx * (corners[3] - corners[2])


@wp.func
def bilinear(corners: Any, fy: Any, fx: Any):
    """Value at fractions (fy, fx) inside a cell from its corner values (00, 01, 10, 11)."""
    top, bottom = along_x(corners, fx)
    return top + fy * (bottom - top)


@wp.func
def slide_taps(window: Any, values: Any, weighted: Any, total: Any, upper: Any):
    """TAPS sources along a source row against the gradients of TAPS tap columns, from registers: source u meets tap
    m's gradient at window[u + m] (window[0 .. TAPS - 2] held from before, window[TAPS - 1 ..] the block's loads);
    ``total`` sums v g, ``upper`` fx v g (``weighted`` = v fx: the upper corners' share along x). The window then moves
    on by TAPS. Returns (window, total, upper)."""
    for u in range(TAPS):
        for m in range(TAPS):
            total[m] = total[m] + window[u + m] * values[u]
            upper[m] = upper[m] + window[u + m] * weighted[u]
    for m in range(TAPS - 1):
        window[m] = window[TAPS + m]
    return window, total, upper


@wp.func
def slide_tap(window: Any, value: Any, fraction: Any, total: Any, upper: Any):
    """`slide_taps` for one source (the row's last ones): its gradients at window[0 .. TAPS - 1], the window then
    moves on by one. Returns (window, total, upper)."""
    for m in range(TAPS):
        total[m] = total[m] + window[m] * value
        upper[m] = upper[m] + window[m] * (value * fraction)
    for m in range(TAPS - 1):
        window[m] = window[m + 1]
    return window, total, upper


@wp.func
def fold_row(total: Any, upper: Any, fy: Any, s00: Any, s01: Any, s10: Any, s11: Any):
    """A source row's sums folded into the four corners' (00, 01, 10, 11) with its fraction ``fy`` along y: the
    weights are separable, (1 - fy, fy) x (1 - fx, fx). Returns (s00, s01, s10, s11)."""
    one = type(fy)(1.0)
    lower = total - upper
    return s00 + (one - fy) * lower, s01 + (one - fy) * upper, s10 + fy * lower, s11 + fy * upper


@wp.func
def write_partials(partials: Any, slot: int, c: int, cell: int, i: int, j0: int, size: int, s00: Any, s01: Any,
                   s10: Any, s11: Any):
    """A thread's corner sums of taps (i, j0 .. j0 + TAPS - 1) into its partial slot (the taps past K left out)."""
    for m in range(TAPS):
        if j0 + m < size:
            partials[slot, c, cell, i * size + j0 + m] = wp.vector(s00[m], s01[m], s10[m], s11[m])


@wp.kernel
def psf_backward_cells(
    source: wp.array3d(dtype=Any),
    padded_grad: wp.array3d(dtype=Any),
    row_bounds: wp.array(dtype=wp.int32),
    row_frac: wp.array(dtype=Any),
    col_bounds: wp.array(dtype=wp.int32),
    col_frac: wp.array(dtype=Any),
    size: int,
    channels: int,
    cells_y: int,
    cells_x: int,
    row_chunks: int,
    col_chunks: int,
    partials: wp.array4d(dtype=Any),
):
    """dL/dcell_n(d) for the four corners of each cell: sum over the cell's sources s of x(s) times the gradient
    of the output s reached under tap d, times s's bilinear corner weights.

    Thread (lane, tap group): the tap group enumerates (c, i, TAPS consecutive j); the lane (b, cell, chunk of the
    cell's source rows, chunk of its columns). Neighbouring threads share a source row, so its loads are broadcast.
    Along the row the gradients of the TAPS outputs slide through registers (one load per source), TAPS sources a
    block with every load of a block issued before its arithmetic (else the kernel waits on its loads one source at
    a time: docs/benchmarks.md, PSF convolution); the weights are separable, so
    each row keeps two sums per tap (sum v and sum fx * v, v = g x) and folds them into the four corners with its
    fy. Each thread writes its own partials[(b, row chunk, column chunk), c, cell, tap] (summed over batch and
    chunks by the caller): no atomics.
    """
    lane, group = wp.tid()
    groups = (size + TAPS - 1) / TAPS
    j0 = (group % groups) * TAPS
    i = (group / groups) % size
    c = group / (groups * size)
    chunks = row_chunks * col_chunks
    chunk = lane % chunks
    row_chunk = chunk / col_chunks
    col_chunk = chunk % col_chunks
    cell = (lane / chunks) % (cells_y * cells_x)
    b = lane / (chunks * cells_y * cells_x)
    cy = cell / cells_x
    cx = cell % cells_x
    bc = b * channels + c
    rows = row_bounds[cy + 1] - row_bounds[cy]
    per_chunk = (rows + row_chunks - 1) / row_chunks
    s_start = row_bounds[cy] + row_chunk * per_chunk
    s_stop = wp.min(s_start + per_chunk, row_bounds[cy + 1])
    cols = col_bounds[cx + 1] - col_bounds[cx]
    per_chunk = (cols + col_chunks - 1) / col_chunks
    t_first = col_bounds[cx] + col_chunk * per_chunk
    t_end = wp.min(t_first + per_chunk, col_bounds[cx + 1])
    s00 = wp.vector(length=TAPS, dtype=source.dtype)
    s01 = wp.vector(length=TAPS, dtype=source.dtype)
    s10 = wp.vector(length=TAPS, dtype=source.dtype)
    s11 = wp.vector(length=TAPS, dtype=source.dtype)
    # the gradients along the row: before source t is taken, window[0 .. TAPS - 2] hold padded_grad at t + j0 + 0 ..
    # TAPS - 2 (relative to the row's `grads`); a block of TAPS sources loads the next TAPS into window[TAPS - 1 ..],
    # so source t + u reads window[u .. u + TAPS - 1] by constant indices, and its loads are all in flight at once
    window = wp.vector(length=wp.static(2 * TAPS - 1), dtype=source.dtype)
    values = wp.vector(length=TAPS, dtype=source.dtype)
    weighted = wp.vector(length=TAPS, dtype=source.dtype)
    blocks = wp.max(t_end - t_first, 0) / TAPS  # an empty chunk (wide, short cells on a GPU) has none
    for s in range(s_start, s_stop):
        grads = (bc * padded_grad.shape[1] + s + i) * padded_grad.shape[2] + j0  # padded_grad[bc, s + i, j0 + 0]
        sources = (bc * source.shape[1] + s) * source.shape[2]  # source[bc, s, 0]
        for m in range(TAPS - 1):
            window[m] = load(padded_grad, grads + t_first + m)
        total = wp.vector(length=TAPS, dtype=source.dtype)
        upper = wp.vector(length=TAPS, dtype=source.dtype)
        for block in range(blocks):
            t = t_first + block * TAPS
            for u in range(TAPS):
                window[TAPS - 1 + u] = load(padded_grad, grads + t + TAPS - 1 + u)
                values[u] = load(source, sources + t + u)
                weighted[u] = values[u] * load(col_frac, t + u)
            window, total, upper = slide_taps(window, values, weighted, total, upper)
        for t in range(t_first + blocks * TAPS, t_end):  # the last sources, one at a time
            window[TAPS - 1] = load(padded_grad, grads + t + TAPS - 1)
            window, total, upper = slide_tap(window, load(source, sources + t), load(col_frac, t), total, upper)
        s00, s01, s10, s11 = fold_row(total, upper, row_frac[s], s00, s01, s10, s11)
    write_partials(partials, b * chunks + chunk, c, cell, i, j0, size, s00, s01, s10, s11)


for _float, _vec4 in ((wp.float32, wp.vec4f), (wp.float64, wp.vec4d)):
    _planes = wp.array3d(dtype=_float)
    _cells = wp.array4d(dtype=_vec4)
    _table = wp.array(dtype=_float)
    _index = wp.array(dtype=wp.int32)
    wp.overload(psf_backward_cells, [_planes, _planes, _index, _table, _index, _table, int, int, int, int, int, int,
                                     wp.array4d(dtype=_vec4)])


STAGED_ROWS = 8  # source rows a block of the staged PSF adjoint takes into shared memory at a time
STAGED_COLS = 64  # source columns of one block of the staged PSF adjoint (a cell wider is split into column chunks)


class StagedTiles(NamedTuple):
    """The staged PSF adjoint's block for PSFs of ``size`` taps (`staged_tiles`)."""

    groups: int  # tap groups (TAPS consecutive tap columns) a tap row
    threads: int  # threads a block: the tap groups of one channel, in whole warps
    rows: int  # gradient rows a block's STAGED_ROWS sources reach
    cols: int  # gradient columns its STAGED_COLS sources reach through every tap group
    elements: int  # shared-memory elements a block: the gradient tile, its sources and their column fractions


def staged_tiles(size: int) -> StagedTiles:
    """`StagedTiles` of PSFs of ``size`` x ``size`` taps: the one place their sizes are derived (the kernel's tile
    shapes, the op's launch and padding)."""
    groups = (size + TAPS - 1) // TAPS
    rows, cols = STAGED_ROWS + size - 1, STAGED_COLS + groups * TAPS - 1
    return StagedTiles(groups, -(-size * groups // 32) * 32, rows, cols,
                       rows * cols + STAGED_ROWS * STAGED_COLS + STAGED_COLS)


@functools.lru_cache(maxsize=None)
def psf_cells_staged(size: int) -> wp.Kernel:
    """The PSF adjoint with the gradient rows a block reads staged in shared memory (float32 and float64 overloads,
    a Warp module of its own per size): the same sums as `psf_backward_cells`, read as tiles.

    Why: in `psf_backward_cells` the 32 threads of a warp are 32 tap groups, each reading the gradient of another
    row, so each of its window loads takes 32 sectors (most of the kernel's sectors excessive: docs/benchmarks.md,
    PSF convolution) and the kernel waits on L1. Here a block is one (image, channel, cell,
    row split, column chunk); its threads are the tap groups (tap row i, TAPS consecutive tap columns from j0) of
    one channel, and it loads the STAGED_ROWS x STAGED_COLS sources of a step and the gradient rows and columns
    they reach as tiles into shared memory (coalesced, once), then each thread slides its window along its
    gradient row there (a thread a row: distinct banks but for rows 8 apart). Partial sums per (image, split) as in
    `psf_backward_cells`: no atomics, deterministic.

    Grid: (blocks, threads), blocks = planes * cells * row splits * column chunks, launched in blocks of
    ``threads`` (`staged_tiles`); every column chunk at most STAGED_COLS wide. The planes come as 2D views [planes *
    rows, columns] (``source_rows``, ``grad_rows`` a plane) read without bounds checks (the checks took more
    instructions than the sums): the op layer pads them so that every tile a block loads lies inside its plane
    and gives ``col_frac`` STAGED_COLS more entries.
    """
    groups, _, tile_rows, tile_cols, _ = staged_tiles(size)

    @wp.kernel(module="unique", enable_backward=False)
    def psf_backward_staged(
        source: wp.array2d(dtype=Any),
        source_rows: int,
        padded_grad: wp.array2d(dtype=Any),
        grad_rows: int,
        row_bounds: wp.array(dtype=wp.int32),
        row_frac: wp.array(dtype=Any),
        col_bounds: wp.array(dtype=wp.int32),
        col_frac: wp.array(dtype=Any),
        channels: int,
        cells_y: int,
        cells_x: int,
        row_splits: int,
        col_chunks: int,
        partials: wp.array4d(dtype=Any),
    ):
        block, lane = wp.tid()
        splits = row_splits * col_chunks
        split = block % splits
        cell = (block / splits) % (cells_y * cells_x)
        bc = block / (splits * cells_y * cells_x)
        cy = cell / cells_x
        cx = cell % cells_x
        rows = row_bounds[cy + 1] - row_bounds[cy]
        per_split = (rows + row_splits - 1) / row_splits
        s_begin = row_bounds[cy] + (split / col_chunks) * per_split
        s_end = wp.min(s_begin + per_split, row_bounds[cy + 1])
        cols = col_bounds[cx + 1] - col_bounds[cx]
        per_chunk = (cols + col_chunks - 1) / col_chunks
        t_first = col_bounds[cx] + (split % col_chunks) * per_chunk
        width = wp.max(wp.min(t_first + per_chunk, col_bounds[cx + 1]) - t_first, 0)
        i = lane / wp.static(groups)
        j0 = (lane % wp.static(groups)) * TAPS
        active = i < wp.static(size)
        s00 = wp.vector(length=TAPS, dtype=source.dtype)
        s01 = wp.vector(length=TAPS, dtype=source.dtype)
        s10 = wp.vector(length=TAPS, dtype=source.dtype)
        s11 = wp.vector(length=TAPS, dtype=source.dtype)
        window = wp.vector(length=wp.static(2 * TAPS - 1), dtype=source.dtype)
        values = wp.vector(length=TAPS, dtype=source.dtype)
        weighted = wp.vector(length=TAPS, dtype=source.dtype)
        blocks = width / TAPS
        s0 = s_begin
        while s0 < s_end:  # the same steps in every thread of the block: the tile loads are the block's
            grads = wp.tile_load(padded_grad, shape=(tile_rows, tile_cols), offset=(bc * grad_rows + s0, t_first),
                                 storage="shared", bounds_check=False)
            sources = wp.tile_load(source, shape=(STAGED_ROWS, STAGED_COLS), offset=(bc * source_rows + s0, t_first),
                                   storage="shared", bounds_check=False)
            fractions = wp.tile_load(col_frac, shape=(STAGED_COLS,), offset=(t_first,), storage="shared",
                                     bounds_check=False)
            if active:
                for r in range(wp.min(STAGED_ROWS, s_end - s0)):
                    g = r + i  # this thread's gradient row in the tile
                    for m in range(TAPS - 1):
                        window[m] = grads[g, j0 + m]
                    total = wp.vector(length=TAPS, dtype=source.dtype)
                    upper = wp.vector(length=TAPS, dtype=source.dtype)
                    for step in range(blocks):
                        t = step * TAPS
                        for u in range(TAPS):
                            window[TAPS - 1 + u] = grads[g, t + j0 + TAPS - 1 + u]
                            values[u] = sources[r, t + u]
                            weighted[u] = values[u] * fractions[t + u]
                        window, total, upper = slide_taps(window, values, weighted, total, upper)
                    for t in range(blocks * TAPS, width):  # the last sources, one at a time
                        window[TAPS - 1] = grads[g, t + j0 + TAPS - 1]
                        window, total, upper = slide_tap(window, sources[r, t], fractions[t], total, upper)
                    s00, s01, s10, s11 = fold_row(total, upper, row_frac[s0 + r], s00, s01, s10, s11)
            s0 += STAGED_ROWS
        if active:
            write_partials(partials, (bc / channels) * splits + split, bc % channels, cell, i, j0, wp.static(size),
                           s00, s01, s10, s11)

    for _float, _vec4 in ((wp.float32, wp.vec4f), (wp.float64, wp.vec4d)):
        planes, table, index = wp.array2d(dtype=_float), wp.array(dtype=_float), wp.array(dtype=wp.int32)
        wp.overload(psf_backward_staged, [planes, int, planes, int, index, table, index, table, int, int, int, int,
                                          int, wp.array4d(dtype=_vec4)])
    return psf_backward_staged


class PsfKernels(NamedTuple):
    forward: wp.Kernel
    backward_source: wp.Kernel


@functools.lru_cache(maxsize=None)
def psf_kernels(size: int) -> PsfKernels:
    """The forward and image-adjoint kernels for PSFs of ``size`` x ``size`` taps (float32 and float64 overloads,
    in a Warp module of their own per size).

    Thread ([part,] plane, row group, column) keeps ROWS outputs (or source gradients) in registers and walks the
    tap columns j (the forward: those of its part). For each it loads the WINDOW = size + ROWS - 1 values of its
    column that the size x ROWS (tap row, output) pairs read, once, then runs every tap row from registers: 0.18
    loads per tap and output at size 15, where register tiles of outputs need 0.3 in the forward and 1 in the image
    adjoint. ``size`` is a compile-time constant, so the tap-row and window loops unroll and the window is indexed
    by constants: registers, not local memory.

    Grids: forward (parts, planes, ceil(H / ROWS), W) over outputs, part p taking tap columns p * taps .. p * taps +
    taps - 1 into out[p] (the caller sums the parts: one part, taps = size, unless a launch is too small to fill the
    GPU); image adjoint (planes, ceil((H + 2r) / ROWS), W + 2r) over padded sources, whose gradients the caller folds
    back onto the border pixels.
    """
    window = size + ROWS - 1

    @wp.kernel(module="unique", enable_backward=False, launch_bounds=FORWARD_BOUNDS)
    def psf_forward(
        source: wp.array3d(dtype=Any),
        cells: wp.array4d(dtype=Any),
        cells_x: int,
        row_cell: wp.array(dtype=wp.int32),
        row_frac: wp.array(dtype=Any),
        row_bounds: wp.array(dtype=wp.int32),
        col_cell: wp.array(dtype=wp.int32),
        col_frac: wp.array(dtype=Any),
        taps: int,
        out: wp.array4d(dtype=Any),
    ):
        part, bc, group, x = wp.tid()
        j_begin = part * taps  # this thread's share of the tap columns (all of them unless the launch is split)
        j_end = wp.min(j_begin + taps, size)
        c = bc % cells.shape[0]
        y = group * ROWS
        pitch = source.shape[2]
        # flat offsets: source[bc, y, x + size - 1] (tap column j reads source column t = x + size - 1 - j, window
        # row r at + r * pitch) and the PSF cells of channel c (cell n's tap (i, j) at + (n * size + i) * size + j)
        corner = (bc * source.shape[1] + y) * pitch + x + size - 1
        channel = c * cells.shape[1]
        # the window: padded source rows y .. y + WINDOW - 1; output y + k reads window row size - 1 - i + k under
        # tap row i. Its rows lie in one grid cell, or in two split at `split` (cells taller than the window, as
        # in every image the size of the kernel's window or more per cell), or in more
        fy = wp.vector(length=wp.static(window), dtype=source.dtype)
        for r in range(wp.static(window)):
            fy[r] = row_frac[y + r]
        first = row_cell[y]
        last = row_cell[y + window - 1]
        split = window
        if last != first:
            split = row_bounds[first + 1] - y
        acc = wp.vector(length=ROWS, dtype=source.dtype)
        value = wp.vector(length=wp.static(window), dtype=source.dtype)
        if last == first:
            # the whole window in one cell (most threads): a loop without branches, small enough for the
            # instruction cache
            cell = channel + first * cells_x
            for j in range(j_begin, j_end):
                t = x + size - 1 - j
                fx = col_frac[t]
                nodes = (cell + col_cell[t]) * wp.static(size * size) + j
                for r in range(wp.static(window)):
                    value[r] = load(source, corner - j + r * pitch)
                for i in range(wp.static(size)):
                    low, high = along_x(load_node(cells, nodes + i * size), fx)
                    slope = high - low
                    for k in range(wp.static(ROWS)):
                        acc[k] = acc[k] + value[size - 1 - i + k] * (low + fy[size - 1 - i + k] * slope)
        elif last - first == 1:
            # two cells (the window straddles a cell row): both cells' PSFs interpolated along x once per tap,
            # each output taking the one its row lies in
            top = channel + first * cells_x
            bottom = channel + last * cells_x
            for j in range(j_begin, j_end):
                t = x + size - 1 - j
                fx = col_frac[t]
                column = col_cell[t]
                nodes_top = (top + column) * wp.static(size * size) + j
                nodes_bottom = (bottom + column) * wp.static(size * size) + j
                for r in range(wp.static(window)):
                    value[r] = load(source, corner - j + r * pitch)
                for i in range(wp.static(size)):
                    r0 = size - 1 - i
                    low_top, high_top = along_x(load_node(cells, nodes_top + i * size), fx)
                    low_bottom, high_bottom = along_x(load_node(cells, nodes_bottom + i * size), fx)
                    slope_top = high_top - low_top
                    slope_bottom = high_bottom - low_bottom
                    for k in range(wp.static(ROWS)):
                        below = r0 + k >= split
                        low = wp.where(below, low_bottom, low_top)
                        slope = wp.where(below, slope_bottom, slope_top)
                        acc[k] = acc[k] + value[r0 + k] * (low + fy[r0 + k] * slope)
        else:
            # more cells (cells shorter than the window): each output's own cell
            for j in range(j_begin, j_end):
                t = x + size - 1 - j
                fx = col_frac[t]
                column = col_cell[t]
                for r in range(wp.static(window)):
                    value[r] = load(source, corner - j + r * pitch)
                for i in range(wp.static(size)):
                    r0 = size - 1 - i
                    for k in range(wp.static(ROWS)):
                        nodes = (channel + row_cell[y + r0 + k] * cells_x + column) * wp.static(size * size)
                        node = load_node(cells, nodes + i * size + j)
                        acc[k] = acc[k] + value[r0 + k] * bilinear(node, fy[r0 + k], fx)
        height = out.shape[2]
        for k in range(ROWS):
            if y + k < height:
                out[part, bc, y + k, x] = acc[k]

    @wp.kernel(module="unique", enable_backward=False, launch_bounds=FORWARD_BOUNDS)
    def psf_backward_source(
        padded_grad: wp.array3d(dtype=Any),
        cells: wp.array4d(dtype=Any),
        cells_x: int,
        row_cell: wp.array(dtype=wp.int32),
        row_frac: wp.array(dtype=Any),
        col_cell: wp.array(dtype=wp.int32),
        col_frac: wp.array(dtype=Any),
        grad_source: wp.array3d(dtype=Any),
    ):
        bc, group, t = wp.tid()
        c = bc % cells.shape[0]
        s = group * ROWS
        fx = col_frac[t]
        column = col_cell[t]
        pitch = padded_grad.shape[2]
        corner = (bc * padded_grad.shape[1] + s) * pitch + t  # padded_grad[bc, s, t]
        channel = c * cells.shape[1]
        fy = wp.vector(length=ROWS, dtype=padded_grad.dtype)
        nodes = wp.vector(length=ROWS, dtype=wp.int32)  # cells[c, cell of source s + k, 0, 0]
        for k in range(ROWS):
            fy[k] = row_frac[s + k]
            nodes[k] = (channel + row_cell[s + k] * cells_x + column) * wp.static(size * size)
        acc = wp.vector(length=ROWS, dtype=padded_grad.dtype)
        # source s + k gathers padded_grad[s + k + i, t + j] under tap (i, j): window row i + k of column t + j
        grad = wp.vector(length=wp.static(window), dtype=padded_grad.dtype)
        if nodes[0] == nodes[ROWS - 1]:
            for j in range(cells.shape[2]):
                for r in range(wp.static(window)):
                    grad[r] = load(padded_grad, corner + j + r * pitch)
                for i in range(wp.static(size)):
                    low, high = along_x(load_node(cells, nodes[0] + i * size + j), fx)
                    slope = high - low
                    for k in range(wp.static(ROWS)):
                        acc[k] = acc[k] + grad[i + k] * (low + fy[k] * slope)
        else:
            for j in range(cells.shape[2]):
                for r in range(wp.static(window)):
                    grad[r] = load(padded_grad, corner + j + r * pitch)
                for i in range(wp.static(size)):
                    for k in range(wp.static(ROWS)):
                        node = load_node(cells, nodes[k] + i * size + j)
                        acc[k] = acc[k] + grad[i + k] * bilinear(node, fy[k], fx)
        rows = grad_source.shape[1]
        for k in range(ROWS):
            if s + k < rows:
                grad_source[bc, s + k, t] = acc[k]

    for _float, _vec4 in ((wp.float32, wp.vec4f), (wp.float64, wp.vec4d)):
        planes, cells, table, index = (wp.array3d(dtype=_float), wp.array4d(dtype=_vec4), wp.array(dtype=_float),
                                       wp.array(dtype=wp.int32))
        wp.overload(psf_forward, [planes, cells, int, index, table, index, index, table, int,
                                  wp.array4d(dtype=_float)])
        wp.overload(psf_backward_source, [planes, cells, int, index, table, index, table, planes])
    return PsfKernels(psf_forward, psf_backward_source)
