"""Batch normalisation with batch statistics followed by ReLU, over channels-last activations, as Warp kernels:

    y = max(a (x - mean) + bias, 0),   a = weight / sqrt(var + eps),

mean and the biased var per channel over the R = B H W rows of x [R, C] (Ioffe and Szegedy 2015, training mode;
torch.nn.functional.batch_norm followed by relu, docs/references.md). The backward, with g = dy where
a (x - mean) + bias > 0 (else 0, torch's threshold_backward) and the sums over the rows,

    dbias = sum g,   dweight = invstd sum g (x - mean),
    dx = a g + k1 (x - mean) + k0,   k1 = -a invstd^2 sum g (x - mean) / R,   k0 = -a sum g / R.

The ReLU's mask is recomputed from x (the same `affine` as the forward's), so neither y nor a mask is stored.

Layout: each thread owns a pair of channels (2p, 2p + 1) and walks the rows g, g + G, g + 2G, ... of x [R, C], so a
warp's loads are one contiguous run of memory. bfloat16 data comes as int32 words [R, C / 2], one pair per 4-byte
load (two bfloat16 loads would halve the bytes per instruction; more channels a thread in one wider load need
more registers, leaving fewer warps to hide the loads); float32 and float64 data as [R, C]. Arithmetic is float32
for bfloat16 and float32, float64 for float64. The reductions write
one partial sum per row group [G, 2, C] in a fixed order (the op adds them up): deterministic, no atomics. The
statistics sum x - x[0] (a shift inside the data's range keeps E[x^2] - E[x]^2 from cancelling).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

UNROLL = 4  # rows a thread loads before it uses them: four loads in flight per thread


# bit casts between float32 and its 32 bits: CUDA's intrinsics on the GPU, memcpy (the defined form) on the CPU
_BITS = """
#if defined(__CUDA_ARCH__)
#define WS_FLOAT_BITS(f) __float_as_uint(f)
#define WS_BITS_FLOAT(u) __uint_as_float(u)
#else
#define WS_FLOAT_BITS(f) ([](float v) { unsigned int u; __builtin_memcpy(&u, &v, 4); return u; }(f))
#define WS_BITS_FLOAT(u) ([](unsigned int v) { float f; __builtin_memcpy(&f, &v, 4); return f; }(u))
#endif
"""


@wp.func_native(_BITS + "return WS_BITS_FLOAT(((unsigned int)word) << 16u);")
def bf16_low(word: wp.int32) -> float:
    """The bfloat16 in the low half of ``word`` (the pair's first channel, little-endian), as float32."""
    ...


@wp.func_native(_BITS + "return WS_BITS_FLOAT(((unsigned int)word) & 0xFFFF0000u);")
def bf16_high(word: wp.int32) -> float:
    """The bfloat16 in the high half of ``word`` (the pair's second channel), as float32."""
    ...


@wp.func_native(_BITS + """unsigned int bits[2] = {WS_FLOAT_BITS(low), WS_FLOAT_BITS(high)};
for (int i = 0; i < 2; ++i) {
    if ((bits[i] & 0x7FFFFFFFu) > 0x7F800000u) bits[i] = 0x7FC00000u;  // NaN stays NaN
    else bits[i] += 0x7FFFu + ((bits[i] >> 16u) & 1u);                 // round to nearest, ties to even
}
return (int)((bits[1] & 0xFFFF0000u) | (bits[0] >> 16u));""")
def bf16_pair(low: float, high: float) -> wp.int32:
    """Two float32 values rounded to bfloat16 (nearest, ties to even, as torch's casts) and packed into one word."""
    ...


# Element (r, c) of the contiguous rows [R, C] (or [R, C / 2] words) at r * width + c, in 64 bits: Warp's x[r, c]
# also wraps negative indices and multiplies a 64-bit stride per axis on every access, more instructions than the
# arithmetic here (docs/benchmarks.md, PSF convolution).
_AT = "return a.data[(long long)r * a.shape[1] + c];"
_PUT = "a.data[(long long)r * a.shape[1] + c] = v;"


@wp.func_native(_AT)
def at(a: wp.array2d(dtype=wp.int32), r: int, c: int) -> wp.int32: ...


@wp.func_native(_AT)
def at(a: wp.array2d(dtype=wp.float32), r: int, c: int) -> wp.float32: ...  # noqa: F811 (overloads by dtype)


@wp.func_native(_AT)
def at(a: wp.array2d(dtype=wp.float64), r: int, c: int) -> wp.float64: ...  # noqa: F811


@wp.func_native(_PUT)
def put(a: wp.array2d(dtype=wp.int32), r: int, c: int, v: wp.int32): ...


@wp.func_native(_PUT)
def put(a: wp.array2d(dtype=wp.float32), r: int, c: int, v: wp.float32): ...  # noqa: F811


@wp.func_native(_PUT)
def put(a: wp.array2d(dtype=wp.float64), r: int, c: int, v: wp.float64): ...  # noqa: F811


@wp.func
def load_pair(x: wp.array2d(dtype=wp.int32), r: int, p: int):
    """Channels 2p and 2p + 1 of row r, in the arithmetic type."""
    word = at(x, r, p)
    return wp.vec2f(bf16_low(word), bf16_high(word))


@wp.func
def load_pair(x: wp.array2d(dtype=wp.float32), r: int, p: int):  # noqa: F811  - overloads by the array's dtype
    return wp.vec2f(at(x, r, 2 * p), at(x, r, 2 * p + 1))


@wp.func
def load_pair(x: wp.array2d(dtype=wp.float64), r: int, p: int):  # noqa: F811
    return wp.vec2d(at(x, r, 2 * p), at(x, r, 2 * p + 1))


@wp.func
def store_pair(y: wp.array2d(dtype=wp.int32), r: int, p: int, value: wp.vec2f):
    put(y, r, p, bf16_pair(value[0], value[1]))


@wp.func
def store_pair(y: wp.array2d(dtype=wp.float32), r: int, p: int, value: wp.vec2f):  # noqa: F811
    put(y, r, 2 * p, value[0])
    put(y, r, 2 * p + 1, value[1])


@wp.func
def store_pair(y: wp.array2d(dtype=wp.float64), r: int, p: int, value: wp.vec2d):  # noqa: F811
    put(y, r, 2 * p, value[0])
    put(y, r, 2 * p + 1, value[1])


@wp.func
def affine(value: Any, mean: Any, scale: Any, bias: Any):
    """a (x - mean) + bias per channel (= a x + b; centred first, so that x far from 0 loses no precision): the
    forward's ReLU input, recomputed the same way by the backward for its mask."""
    return wp.cw_mul(value - mean, scale) + bias


@wp.func
def relu_mask(value: Any, z: Any):
    """``value`` where z > 0, else 0, per channel."""
    zero = type(z[0])(0.0)
    return type(value)(wp.where(z[0] > zero, value[0], zero), wp.where(z[1] > zero, value[1], zero))


@wp.func
def pair_thread(t: int, pairs: int):
    """Thread t of a one-dimensional launch -> (row group, channel pair); pairs fastest."""
    return t / pairs, t % pairs


@wp.func
def write_partials(partials: wp.array3d(dtype=Any), group: int, p: int, first: Any, second: Any):
    partials[group, 0, 2 * p] = first[0]
    partials[group, 0, 2 * p + 1] = first[1]
    partials[group, 1, 2 * p] = second[0]
    partials[group, 1, 2 * p + 1] = second[1]


@wp.func
def load_rows(x: wp.array2d(dtype=Any), start: int, groups: int, p: int, zero: Any):
    """Channels 2p and 2p + 1 of rows start + u groups, u < UNROLL, all loaded before any is used; rows past the
    end read as 0. ``zero`` is a zero pair of the arithmetic type."""
    v = wp.vector(length=wp.static(2 * UNROLL), dtype=type(zero[0]))
    for u in range(wp.static(UNROLL)):
        r = start + u * groups
        if r < x.shape[0]:
            value = load_pair(x, r, p)
            v[2 * u] = value[0]
            v[2 * u + 1] = value[1]
    return v


@wp.func
def pair_at(v: Any, u: int, zero: Any):
    """Row u's pair of a `load_rows` vector."""
    return type(zero)(v[2 * u], v[2 * u + 1])


@wp.kernel
def batch_sums(x: wp.array2d(dtype=Any), pairs: int, groups: int, partials: wp.array3d(dtype=Any)):
    """partials[g, 0] = sum (x - x[0]), partials[g, 1] = sum (x - x[0])^2 over row group g's rows."""
    group, p = pair_thread(wp.tid(), pairs)
    shift = load_pair(x, 0, p)
    zero = shift - shift
    first = zero
    second = zero
    for start in range(group, x.shape[0], groups * UNROLL):
        v = load_rows(x, start, groups, p, zero)
        for u in range(wp.static(UNROLL)):
            r = start + u * groups
            if r < x.shape[0]:
                value = pair_at(v, u, zero) - shift
                first += value
                second += wp.cw_mul(value, value)
    write_partials(partials, group, p, first, second)


@wp.kernel
def batch_statistics(x: wp.array2d(dtype=Any), sums: wp.array2d(dtype=Any), weight: wp.array(dtype=Any),
                     bias: wp.array(dtype=Any), eps: Any, stats: wp.array2d(dtype=Any)):
    """Thread c: channel c's mean, 1 / sqrt(var + eps), a, bias and the biased var into stats[0..4, c], from ``sums``
    [2, C] (the partials added up)."""
    c = wp.tid()
    count = type(sums[0, c])(x.shape[0])
    shifted = sums[0, c] / count
    mean = load_pair(x, 0, c / 2)[c % 2] + shifted
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
def pair_of(stats: wp.array2d(dtype=Any), row: int, p: int):
    """Channels 2p and 2p + 1 of row ``row`` of a per-channel table [rows, C]."""
    return wp.vector(stats[row, 2 * p], stats[row, 2 * p + 1])


@wp.kernel
def normalize_relu(x: wp.array2d(dtype=Any), pairs: int, groups: int, stats: wp.array2d(dtype=Any),
                   y: wp.array2d(dtype=Any)):
    """y = max(a (x - mean) + bias, 0) for row group g's rows."""
    group, p = pair_thread(wp.tid(), pairs)
    mean = pair_of(stats, 0, p)
    scale = pair_of(stats, 2, p)
    bias = pair_of(stats, 3, p)
    zero = scale - scale
    for start in range(group, x.shape[0], groups * UNROLL):
        v = load_rows(x, start, groups, p, zero)
        for u in range(wp.static(UNROLL)):
            r = start + u * groups
            if r < x.shape[0]:
                store_pair(y, r, p, wp.max(affine(pair_at(v, u, zero), mean, scale, bias), zero))


@wp.kernel
def gradient_sums(grad_y: wp.array2d(dtype=Any), x: wp.array2d(dtype=Any), pairs: int, groups: int,
                  stats: wp.array2d(dtype=Any), partials: wp.array3d(dtype=Any)):
    """partials[g, 0] = sum g, partials[g, 1] = sum g (x - mean) over row group g's rows (g: dy through the ReLU)."""
    group, p = pair_thread(wp.tid(), pairs)
    mean = pair_of(stats, 0, p)
    scale = pair_of(stats, 2, p)
    bias = pair_of(stats, 3, p)
    zero = mean - mean
    first = zero
    second = zero
    for start in range(group, x.shape[0], groups * UNROLL):
        v = load_rows(x, start, groups, p, zero)
        d = load_rows(grad_y, start, groups, p, zero)
        for u in range(wp.static(UNROLL)):
            value = pair_at(v, u, zero)
            g = relu_mask(pair_at(d, u, zero), affine(value, mean, scale, bias))  # rows past the end: d = 0
            first += g
            second += wp.cw_mul(g, value - mean)
    write_partials(partials, group, p, first, second)


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
def gradient_input(grad_y: wp.array2d(dtype=Any), x: wp.array2d(dtype=Any), pairs: int, groups: int,
                   stats: wp.array2d(dtype=Any), coefficients: wp.array2d(dtype=Any), grad_x: wp.array2d(dtype=Any)):
    """dx = a g + k1 (x - mean) + k0 for row group g's rows."""
    group, p = pair_thread(wp.tid(), pairs)
    mean = pair_of(stats, 0, p)
    scale = pair_of(stats, 2, p)
    bias = pair_of(stats, 3, p)
    k1 = pair_of(coefficients, 0, p)
    k0 = pair_of(coefficients, 1, p)
    zero = mean - mean
    for start in range(group, x.shape[0], groups * UNROLL):
        v = load_rows(x, start, groups, p, zero)
        d = load_rows(grad_y, start, groups, p, zero)
        for u in range(wp.static(UNROLL)):
            r = start + u * groups
            if r < x.shape[0]:
                value = pair_at(v, u, zero)
                g = relu_mask(pair_at(d, u, zero), affine(value, mean, scale, bias))
                store_pair(grad_x, r, p, wp.cw_mul(scale, g) + wp.cw_mul(k1, value - mean) + k0)


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
