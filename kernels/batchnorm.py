"""Batch normalisation with batch statistics followed by ReLU, over channels-last activations, as Warp kernels:

    y = max(a (x - mean) + bias, 0),   a = weight / sqrt(var + eps),

mean and the biased var per channel over the R = B H W rows of x [R, C] (Ioffe and Szegedy 2015, training mode;
torch.nn.functional.batch_norm followed by relu, docs/references.md). The backward, with g = dy where a (x - mean) + bias > 0
(else 0, torch's threshold_backward) and the sums over the rows,

    dbias = sum g,   dweight = invstd sum g (x - mean),
    dx = a g + k1 (x - mean) + k0,   k1 = -a invstd^2 sum g (x - mean) / R,   k0 = -a sum g / R.

The ReLU's mask is recomputed from x (the same `affine` as the forward's), so neither y nor a mask is stored.

Layout: each thread owns LANES = 8 neighbouring channels (8q .. 8q + 7) and walks the rows g, g + G, g + 2G, ... of
x [R, C], so a warp's loads are one contiguous run of memory. bfloat16 data comes as int32 words [R, C / 2] and a
thread's 8 channels of a row are one 16-byte load (`load_octet`; Warp's own bfloat16 loads are 2 bytes each, and
4-byte loads of channel pairs left the reductions at a quarter of an H200's bandwidth); float32 and float64 data
as [R, C], C a multiple of 8. Arithmetic is float32 for bfloat16 and float32, float64 for float64. The reductions write
one partial sum per row group [G, 2, C] in a fixed order (the op adds them up): deterministic, no atomics. The
statistics sum x - x[0] (a shift inside the data's range keeps E[x^2] - E[x]^2 from cancelling).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

LANES = 8  # channels per thread: one 16-byte load of bfloat16
UNROLL = 2  # rows a thread loads before it uses them

octet32 = wp.types.vector(length=LANES, dtype=wp.float32)
octet64 = wp.types.vector(length=LANES, dtype=wp.float64)

# bit casts between float32 and its 32 bits, and 16-byte accesses: CUDA's intrinsics and vector types on the GPU,
# memcpy (the defined form) on the CPU
_NATIVE = """
#if defined(__CUDA_ARCH__)
#define WS_FLOAT_BITS(f) __float_as_uint(f)
#define WS_BITS_FLOAT(u) __uint_as_float(u)
#define WS_LOAD16(words, p) { const int4 w = *reinterpret_cast<const int4*>(p); \\
    words[0] = (unsigned int)w.x; words[1] = (unsigned int)w.y; words[2] = (unsigned int)w.z; words[3] = (unsigned int)w.w; }
#define WS_STORE16(p, words) { *reinterpret_cast<int4*>(p) = make_int4((int)words[0], (int)words[1], (int)words[2], (int)words[3]); }
#else
#define WS_FLOAT_BITS(f) ([](float v) { unsigned int u; __builtin_memcpy(&u, &v, 4); return u; }(f))
#define WS_BITS_FLOAT(u) ([](unsigned int v) { float f; __builtin_memcpy(&f, &v, 4); return f; }(u))
#define WS_LOAD16(words, p) __builtin_memcpy(words, p, 16)
#define WS_STORE16(p, words) __builtin_memcpy(p, words, 16)
#endif
"""


@wp.func_native(_NATIVE + """unsigned int words[4];
WS_LOAD16(words, wp::address(x, r, 4 * q));
wp::vec_t<8, float> value;
for (int i = 0; i < 4; ++i) {
    value.c[2 * i] = WS_BITS_FLOAT(words[i] << 16u);              // the low half: the first channel (little-endian)
    value.c[2 * i + 1] = WS_BITS_FLOAT(words[i] & 0xFFFF0000u);
}
return value;""")
def load_octet(x: wp.array2d(dtype=wp.int32), r: int, q: int) -> octet32:
    """Channels 8q .. 8q + 7 of row r of bfloat16 data (as int32 words [R, C / 2]), as float32: one 16-byte load."""
    ...


@wp.func
def load_octet(x: wp.array2d(dtype=wp.float32), r: int, q: int):  # noqa: F811  - overloads by the array's dtype
    value = octet32()
    for i in range(LANES):
        value[i] = x[r, LANES * q + i]
    return value


@wp.func
def load_octet(x: wp.array2d(dtype=wp.float64), r: int, q: int):  # noqa: F811
    value = octet64()
    for i in range(LANES):
        value[i] = x[r, LANES * q + i]
    return value


@wp.func_native(_NATIVE + """unsigned int words[4];
for (int i = 0; i < 4; ++i) {
    unsigned int bits[2] = {WS_FLOAT_BITS(value.c[2 * i]), WS_FLOAT_BITS(value.c[2 * i + 1])};
    for (int k = 0; k < 2; ++k) {
        if ((bits[k] & 0x7FFFFFFFu) > 0x7F800000u) bits[k] = 0x7FC00000u;  // NaN stays NaN
        else bits[k] += 0x7FFFu + ((bits[k] >> 16u) & 1u);                 // round to nearest, ties to even
    }
    words[i] = (bits[1] & 0xFFFF0000u) | (bits[0] >> 16u);
}
WS_STORE16(wp::address(y, r, 4 * q), words);""")
def store_octet(y: wp.array2d(dtype=wp.int32), r: int, q: int, value: octet32):
    """Channels 8q .. 8q + 7 of row r, rounded to bfloat16 (nearest, ties to even, as torch's casts): one 16-byte
    store."""
    ...


@wp.func
def store_octet(y: wp.array2d(dtype=wp.float32), r: int, q: int, value: octet32):  # noqa: F811
    for i in range(LANES):
        y[r, LANES * q + i] = value[i]


@wp.func
def store_octet(y: wp.array2d(dtype=wp.float64), r: int, q: int, value: octet64):  # noqa: F811
    for i in range(LANES):
        y[r, LANES * q + i] = value[i]


@wp.func
def octet_of(table: wp.array2d(dtype=Any), row: int, q: int, zero: Any):
    """Channels 8q .. 8q + 7 of one row of a per-channel table [rows, C], typed like ``zero``."""
    value = zero
    for i in range(LANES):
        value[i] = table[row, LANES * q + i]
    return value


@wp.func
def affine(value: Any, mean: Any, scale: Any, bias: Any):
    """a (x - mean) + bias per channel (= a x + b; centred first, so that x far from 0 loses no precision): the
    forward's ReLU input, recomputed the same way by the backward for its mask."""
    return wp.cw_mul(value - mean, scale) + bias


@wp.func
def relu_mask(value: Any, z: Any):
    """``value`` where z > 0, else 0, per channel."""
    masked = value
    for i in range(LANES):
        if not z[i] > type(z[i])(0.0):
            masked[i] = type(z[i])(0.0)
    return masked


@wp.func
def octet_thread(t: int, octets: int):
    """Thread t of a one-dimensional launch -> (row group, channel octet); octets fastest."""
    return t / octets, t % octets


@wp.func
def write_partials(partials: wp.array3d(dtype=Any), group: int, q: int, first: Any, second: Any):
    for i in range(LANES):
        partials[group, 0, LANES * q + i] = first[i]
        partials[group, 1, LANES * q + i] = second[i]


@wp.func
def load_rows(x: wp.array2d(dtype=Any), start: int, groups: int, q: int, zero: Any):
    """Channels 8q .. 8q + 7 of rows start + u groups, u < UNROLL, as the rows of a matrix, all loaded before any
    is used; rows past the end read as 0. ``zero`` is a zero octet of the arithmetic type."""
    rows = wp.matrix(shape=(wp.static(UNROLL), wp.static(LANES)), dtype=type(zero[0]))
    for u in range(wp.static(UNROLL)):
        r = start + u * groups
        if r < x.shape[0]:
            rows[u] = load_octet(x, r, q)
    return rows


@wp.kernel
def batch_sums(x: wp.array2d(dtype=Any), octets: int, groups: int, partials: wp.array3d(dtype=Any)):
    """partials[g, 0] = sum (x - x[0]), partials[g, 1] = sum (x - x[0])^2 over row group g's rows."""
    group, q = octet_thread(wp.tid(), octets)
    shift = load_octet(x, 0, q)
    first = shift - shift
    second = shift - shift
    for start in range(group, x.shape[0], groups * UNROLL):
        rows = load_rows(x, start, groups, q, first)
        for u in range(wp.static(UNROLL)):
            if start + u * groups < x.shape[0]:
                value = rows[u] - shift
                first += value
                second += wp.cw_mul(value, value)
    write_partials(partials, group, q, first, second)


@wp.kernel
def batch_statistics(x: wp.array2d(dtype=Any), sums: wp.array2d(dtype=Any), weight: wp.array(dtype=Any),
                     bias: wp.array(dtype=Any), eps: Any, stats: wp.array2d(dtype=Any)):
    """Thread c: channel c's mean, 1 / sqrt(var + eps), a, bias and the biased var into stats[0..4, c], from ``sums``
    [2, C] (the partials added up)."""
    c = wp.tid()
    count = type(sums[0, c])(x.shape[0])
    shifted = sums[0, c] / count
    mean = load_octet(x, 0, c / LANES)[c % LANES] + shifted
    var = wp.max(sums[1, c] / count - shifted * shifted, type(count)(0.0))
    invstd = type(count)(1.0) / wp.sqrt(var + eps)
    scale = weight[c] * invstd
    stats[0, c] = mean
    stats[1, c] = invstd
    stats[2, c] = scale
    stats[3, c] = bias[c]
    stats[4, c] = var


@wp.kernel
def update_running(stats: wp.array2d(dtype=Any), rows: int, momentum: Any, running_mean: wp.array(dtype=Any),
                   running_var: wp.array(dtype=Any)):
    """Thread c: the running statistics move by ``momentum`` towards the batch's mean and unbiased variance."""
    c = wp.tid()
    one = type(stats[0, c])(1.0)
    count = type(one)(rows)
    running_mean[c] = (one - momentum) * running_mean[c] + momentum * stats[0, c]
    running_var[c] = (one - momentum) * running_var[c] + momentum * stats[4, c] * count / (count - one)


@wp.func
def zero_like(table: wp.array2d(dtype=wp.float32)):
    """The zero octet of a table's arithmetic type."""
    return octet32()


@wp.func
def zero_like(table: wp.array2d(dtype=wp.float64)):  # noqa: F811
    return octet64()


@wp.kernel
def normalize_relu(x: wp.array2d(dtype=Any), octets: int, groups: int, stats: wp.array2d(dtype=Any),
                   y: wp.array2d(dtype=Any)):
    """y = max(a (x - mean) + bias, 0) for row group g's rows."""
    group, q = octet_thread(wp.tid(), octets)
    zero = zero_like(stats)
    mean = octet_of(stats, 0, q, zero)
    scale = octet_of(stats, 2, q, zero)
    bias = octet_of(stats, 3, q, zero)
    for start in range(group, x.shape[0], groups * UNROLL):
        rows = load_rows(x, start, groups, q, zero)
        for u in range(wp.static(UNROLL)):
            r = start + u * groups
            if r < x.shape[0]:
                store_octet(y, r, q, wp.max(affine(rows[u], mean, scale, bias), zero))


@wp.kernel
def gradient_sums(grad_y: wp.array2d(dtype=Any), x: wp.array2d(dtype=Any), octets: int, groups: int,
                  stats: wp.array2d(dtype=Any), partials: wp.array3d(dtype=Any)):
    """partials[g, 0] = sum g, partials[g, 1] = sum g (x - mean) over row group g's rows (g: dy through the ReLU)."""
    group, q = octet_thread(wp.tid(), octets)
    zero = zero_like(stats)
    mean = octet_of(stats, 0, q, zero)
    scale = octet_of(stats, 2, q, zero)
    bias = octet_of(stats, 3, q, zero)
    first = zero
    second = zero
    for start in range(group, x.shape[0], groups * UNROLL):
        rows = load_rows(x, start, groups, q, zero)
        grads = load_rows(grad_y, start, groups, q, zero)
        for u in range(wp.static(UNROLL)):
            value = rows[u]
            g = relu_mask(grads[u], affine(value, mean, scale, bias))  # rows past the end: dy = 0
            first += g
            second += wp.cw_mul(g, value - mean)
    write_partials(partials, group, q, first, second)


@wp.kernel
def gradient_coefficients(sums: wp.array2d(dtype=Any), rows: int, stats: wp.array2d(dtype=Any),
                          grad_affine: wp.array2d(dtype=Any), coefficients: wp.array2d(dtype=Any)):
    """Thread c: dweight and dbias into grad_affine[0..1, c]; k1 and k0 of dx into coefficients[0..1, c]."""
    c = wp.tid()
    count = type(sums[0, c])(rows)
    invstd = stats[1, c]
    scale = stats[2, c]
    grad_affine[0, c] = invstd * sums[1, c]
    grad_affine[1, c] = sums[0, c]
    coefficients[0, c] = -scale * invstd * invstd * sums[1, c] / count
    coefficients[1, c] = -scale * sums[0, c] / count


@wp.kernel
def gradient_input(grad_y: wp.array2d(dtype=Any), x: wp.array2d(dtype=Any), octets: int, groups: int,
                   stats: wp.array2d(dtype=Any), coefficients: wp.array2d(dtype=Any), grad_x: wp.array2d(dtype=Any)):
    """dx = a g + k1 (x - mean) + k0 for row group g's rows."""
    group, q = octet_thread(wp.tid(), octets)
    zero = zero_like(stats)
    mean = octet_of(stats, 0, q, zero)
    scale = octet_of(stats, 2, q, zero)
    bias = octet_of(stats, 3, q, zero)
    k1 = octet_of(coefficients, 0, q, zero)
    k0 = octet_of(coefficients, 1, q, zero)
    for start in range(group, x.shape[0], groups * UNROLL):
        rows = load_rows(x, start, groups, q, zero)
        grads = load_rows(grad_y, start, groups, q, zero)
        for u in range(wp.static(UNROLL)):
            r = start + u * groups
            if r < x.shape[0]:
                value = rows[u]
                g = relu_mask(grads[u], affine(value, mean, scale, bias))
                store_octet(grad_x, r, q, wp.cw_mul(scale, g) + wp.cw_mul(k1, value - mean) + k0)


for _data, _float in ((wp.int32, wp.float32), (wp.float32, wp.float32), (wp.float64, wp.float64)):
    _rows = wp.array2d(dtype=_data)
    _table = wp.array2d(dtype=_float)
    _partials = wp.array3d(dtype=_float)
    _vector = wp.array(dtype=_float)
    wp.overload(batch_sums, [_rows, int, int, _partials])
    wp.overload(batch_statistics, [_rows, _table, _vector, _vector, _float, _table])
    wp.overload(update_running, [_table, int, _float, _vector, _vector])
    wp.overload(normalize_relu, [_rows, int, int, _table, _rows])
    wp.overload(gradient_sums, [_rows, _rows, int, int, _table, _partials])
    wp.overload(gradient_coefficients, [_table, int, _table, _table, _table])
    wp.overload(gradient_input, [_rows, _rows, int, int, _table, _table, _rows])
