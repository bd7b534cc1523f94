"""The one place where torch tensors meet Warp kernels (docs/references.md, convention 4).

- Inputs are wrapped with ``wp.from_torch(t.detach(), requires_grad=False)`` so Warp neither allocates gradients nor
  syncs the device; outputs and input gradients are allocated by torch; grad_output is made contiguous (a copy when
  it is not), never written.
- Kernels launch on torch's current CUDA stream, so they order correctly with the surrounding torch work and can be
  captured in a CUDA graph. Launches are recorded once per signature and replayed (`launch`).
- Kernels run in float32 or float64: float16/bfloat16 inputs (e.g. under autocast) are computed in float32.
- Every op is a `torch.library` custom op (`warp_op`): a fake (meta) implementation gives output shapes without
  running a kernel, the backward is registered with `register_autograd` and is itself a custom op, so
  `torch.compile` and CUDA-graph capture take the ops without graph breaks. Backward ops have no autograd formula
  of their own: double backward raises a clear error. Eager calls that need none of this (no gradient, no tracing
  or modes) skip the dispatcher (`WarpOp`).
"""

from __future__ import annotations

import collections
import functools
import os
from collections.abc import Sequence

import torch
import warp as wp
from torch.autograd import forward_ad

wp.config.log_level = 30  # warnings only: no banner or per-module compile lines


def _init_warp() -> None:
    """wp.init(); on a machine without a CUDA driver, Warp's native library prints a driver warning to stderr on
    every start, which only says what the user knows: silence that one call there."""
    if torch.cuda.is_available():
        wp.init()
        return
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)


_init_warp()
# tiled kernels (`launch`'s block_dim) run their blocks' threads on the CPU too (Warp's cooperative CPU fibers)
wp.config.enable_cpu_blocks = True
ELEMENT_DTYPES = (torch.bfloat16, torch.float32, torch.float64)
"""Element types of the kernels that read and write tensors in their own dtype (the network's and the loss's ops);
tensors of other dtypes are given to them as float32 (`element_dtype`)."""


def element_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype such a kernel takes a tensor of ``dtype`` in: itself if in `ELEMENT_DTYPES`, else float32."""
    return dtype if dtype in ELEMENT_DTYPES else torch.float32


def arithmetic_dtype(dtype: torch.dtype) -> torch.dtype:
    """The float type such kernels compute in for elements of ``dtype``: float64 for float64, else float32."""
    return torch.float64 if dtype == torch.float64 else torch.float32


def kernel_dtype(*tensors: torch.Tensor) -> torch.dtype:
    """The float type the kernels compute in: float64 if any input is float64, else float32."""
    for tensor in tensors:
        if not tensor.is_floating_point():
            raise TypeError(f"expected a floating-point tensor, got {tensor.dtype}")
    return torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32


def prepare(*tensors: torch.Tensor) -> list[torch.Tensor]:
    """Cast inputs to their common kernel dtype and make them contiguous (autograd-tracked casts, no copies when
    nothing changes). All tensors must share one device."""
    dtype = kernel_dtype(*tensors)
    device = tensors[0].device
    for tensor in tensors[1:]:
        if tensor.device != device:
            raise ValueError(f"all inputs must be on one device, got {device} and {tensor.device}")
    # a tensor already right is passed as it is: `.to` would cost a dispatch even then, and inside torch.func.jvp it
    # wraps a constant at the jvp level, where `forward_tangents` can no longer tell it from one with a tangent
    return [t if t.dtype == dtype and t.is_contiguous() else t.to(dtype).contiguous() for t in tensors]


class Vectors:
    """A contiguous torch tensor [..., N] passed to a kernel as an array of N-vectors over its leading dimensions
    (one vector load per element in the kernel)."""

    _TYPES = {(torch.float32, 4): wp.vec4f, (torch.float64, 4): wp.vec4d}

    def __init__(self, tensor: torch.Tensor):
        self.tensor = tensor
        self.warp_dtype = self._TYPES[(tensor.dtype, tensor.shape[-1])]

    @property
    def signature(self):
        return ("vectors", self.tensor.dtype, self.tensor.dim())


def to_warp(tensor) -> wp.array:
    """A Warp view of a contiguous torch tensor (or `Vectors`), without gradient storage."""
    if isinstance(tensor, Vectors):
        return wp.from_torch(tensor.tensor.detach(), dtype=tensor.warp_dtype, requires_grad=False)
    return wp.from_torch(tensor.detach(), requires_grad=False)


_PLAIN_TENSORS = (torch.Tensor, torch.nn.Parameter)


def plain_eager(tensors: Sequence) -> bool:
    """Whether a call on ``tensors`` (a sequence of arguments; non-tensors ignored) is plain eager PyTorch: not
    traced by torch.compile or torch.jit.trace, no torch-function or dispatch mode (fake tensors, make_fx, export),
    no functorch transform (vmap, grad), plain tensors (no subclasses, no torch-function objects such as FX
    proxies). A few attribute reads: cheap beside the dispatch it saves."""
    if (torch.compiler.is_compiling() or torch._C._get_tracing_state() is not None
            or torch._C._is_torch_function_mode_enabled() or torch._C._len_torch_dispatch_stack()
            or torch._C._functorch.peek_interpreter_stack() is not None):
        return False
    arguments = tuple(tensors)
    return not torch._C._has_torch_function(arguments) and all(
        type(x) in _PLAIN_TENSORS for x in arguments if isinstance(x, torch.Tensor))


def forward_tangents(tensors: Sequence) -> bool:
    """Whether a forward-mode AD tangent reaches one of ``tensors`` (a sequence of arguments; non-tensors ignored):
    a dual tensor of `torch.autograd.forward_ad`, or a tensor wrapped by a `torch.func.jvp` level (also jacfwd's and
    hessian's). The ops have reverse-mode formulas only, and torch lets such a call through with no tangent (a dual
    level) or a zero one (torch.func.jvp): a wrong derivative without a word. Inside other functorch transforms
    alone (vmap, grad) there is no tangent to lose. A tensor whose jvp wrapper lies beneath another transform's
    (jacfwd of jacrev, as hessian nests them) is taken to carry one: its tangent cannot be read from outside, so
    there a constant that an op such as ``.to`` has wrapped is refused too."""
    if torch._C._functorch.peek_interpreter_stack() is not None:
        from torch._functorch.pyfunctorch import retrieve_all_functorch_interpreters

        jvp_levels = {interpreter.level() for interpreter in retrieve_all_functorch_interpreters()
                      if interpreter.key() == torch._C._functorch.TransformType.Jvp}
        if not jvp_levels:
            return False
        for x in tensors:
            outermost = True
            while isinstance(x, torch.Tensor) and (level := torch._C._functorch.maybe_get_level(x)) != -1:
                if level in jvp_levels:
                    if not outermost:
                        return True
                    try:
                        if forward_ad.unpack_dual(x).tangent is not None:
                            return True
                    except RuntimeError:  # a wrapper functorch cannot unpack here: assume a tangent
                        return True
                outermost = False
                x = torch._C._functorch.get_unwrapped(x)
        return False
    return forward_ad._current_level >= 0 and any(
        forward_ad.unpack_dual(x).tangent is not None for x in tensors if isinstance(x, torch.Tensor))


def may_keep(like: torch.Tensor) -> bool:
    """Whether a tensor made now from ``like``'s device may be kept and handed to later calls: plain eager mode
    (`plain_eager`), no CUDA-graph capture on its stream (a tensor made there holds its value only once the graph
    replays, and the graph must compute it itself), not inference mode (its tensors cannot be saved for a later
    backward)."""
    return (plain_eager((like,)) and not torch.is_inference_mode_enabled()
            and not (like.is_cuda and torch.cuda.is_current_stream_capturing()))


def scalar_tensor(value: float | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """A 1-element tensor of ``like``'s dtype and device holding ``value`` (kept on the device: no host sync). For a
    Python number it may be a tensor shared with other calls: read it, never write it."""
    if isinstance(value, torch.Tensor):
        if value.numel() != 1:
            raise ValueError(f"expected a scalar (0-d or 1-element) tensor, got shape {tuple(value.shape)}")
        return value.reshape(1).to(device=like.device, dtype=like.dtype)
    # one kept tensor per (value, dtype, device) where that is allowed (`may_keep`): a fill kernel saved a call;
    # elsewhere a new one: a fill kernel, not a host-to-device copy
    if may_keep(like):
        return _kept_scalar(float(value), like.dtype, like.device)
    return torch.full((1,), float(value), device=like.device, dtype=like.dtype)


@functools.lru_cache(maxsize=64)
def _kept_scalar(value: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The shared read-only tensor of `scalar_tensor` (the kernels only read these arguments)."""
    return torch.full((1,), value, device=device, dtype=dtype)


def bfloat16_words(tensor: torch.Tensor) -> torch.Tensor:
    """A contiguous bfloat16 tensor [..., C] (C even) as the int32 words [..., C / 2] that kernels load two
    channels from at once (Warp's bfloat16 loads are 2 bytes each; `kernels/batchnorm.py` unpacks the halves);
    tensors of other dtypes as they are."""
    return tensor.view(torch.int32) if tensor.dtype == torch.bfloat16 else tensor


def kernel_scalar(value: float, dtype: torch.dtype):
    """``value`` as the Warp scalar of ``dtype`` (float32 or float64), for kernel arguments typed like the arrays'
    elements (a Python float would select float32)."""
    return (wp.float64 if dtype == torch.float64 else wp.float32)(value)


OP_NAMESPACE = "warpsense"
class WarpOp:
    """A Warp kernel's `torch.library` custom op, called as a function (what `warp_op` returns; the op itself is
    ``.op``, e.g. for `torch.library.opcheck`).

    A call that none of torch's machinery needs to see runs the implementation directly: plain eager
    (`plain_eager`), no input that requires a gradient (or gradients off), the profiler off, no forward-AD level
    open, no argument mutated. The custom op's dispatch costs host time on every call, which batch-1 inference pays
    per op (docs/benchmarks.md, batch-1 latency). Every other call (autograd, torch.compile,
    torch.jit.trace, fake tensors, vmap, profiling) goes through the op, so it is seen as one node with its fake
    implementation and autograd formula. A CUDA-graph capture in eager mode may take either path: both launch
    the same kernels on the current stream. A call that a forward-mode tangent reaches (`forward_tangents`)
    raises NotImplementedError: the ops have reverse-mode formulas only."""

    def __init__(self, op, function, direct: bool):
        self.op = op
        self.function = function
        self.direct = direct
        functools.update_wrapper(self, function)

    def __call__(self, *args, **kwargs):
        # is_compiling first: dynamo folds it to True and never traces into the host-side checks
        if not torch.compiler.is_compiling():
            arguments = (*args, *kwargs.values())
            if self.direct and self.direct_call(arguments):
                return self.function(*args, **kwargs)
            if forward_tangents(arguments):
                raise NotImplementedError(
                    f"{self.op._qualname}: forward-mode AD (torch.func.jvp, jacfwd, hessian, "
                    "torch.autograd.forward_ad) is not implemented for warpsense's ops; use reverse mode "
                    "(Tensor.backward, torch.autograd.grad)")
        return self.op(*args, **kwargs)

    @staticmethod
    def direct_call(args: Sequence) -> bool:
        """Whether a call with the arguments ``args`` skips the dispatcher (see the class)."""
        if (torch._C._autograd._profiler_enabled() or forward_ad._current_level >= 0
                or not plain_eager(args)):
            return False
        # meta tensors (shape inference, models built on the meta device) take the op's fake implementation: Warp
        # has no meta device ("Unsupported Torch device type meta"). The ops' inputs share one device (checked
        # before the call), and each op's first argument is a tensor: one look
        if args and isinstance(args[0], torch.Tensor) and args[0].is_meta:
            return False
        return not torch.is_grad_enabled() or not any(
            x.requires_grad for x in args if isinstance(x, torch.Tensor))


def warp_op(name: str, fake, backward=None, setup_context=None, mutates_args: tuple[str, ...] = ()):
    """Decorator: register ``function`` (type-annotated, returns new tensors) as the custom op
    ``warpsense::<name>`` with the fake implementation ``fake`` and, optionally, its autograd formula
    (``backward(ctx, *grads)`` and ``setup_context(ctx, inputs, output)``, as for `torch.library.register_autograd`).
    ``mutates_args`` names the tensor arguments the op writes in place (a batch norm's running statistics): such
    an op always goes through the dispatcher, which keeps their version counters. Returns a `WarpOp`."""

    def register(function):
        op = torch.library.custom_op(f"{OP_NAMESPACE}::{name}", function, mutates_args=mutates_args)
        op.register_fake(fake)
        if backward is not None:
            op.register_autograd(backward, setup_context=setup_context)
        return WarpOp(op, function, direct=not mutates_args)

    return register


def save_inputs(ctx, inputs, output) -> None:
    """``setup_context`` of ops whose backward needs exactly their tensor inputs (non-tensors kept in
    ``ctx.arguments``)."""
    ctx.save_for_backward(*(x for x in inputs if isinstance(x, torch.Tensor)))
    ctx.arguments = tuple(x for x in inputs if not isinstance(x, torch.Tensor))


_LAUNCH_CACHE: "collections.OrderedDict" = collections.OrderedDict()
_LAUNCH_CACHE_SIZE = 256
_STREAMS: dict = {}


def _warp_stream(device: torch.device):
    """Warp's view of torch's current CUDA stream (cached per stream handle)."""
    torch_stream = torch.cuda.current_stream(device)
    key = (device.index, torch_stream.cuda_stream)
    stream = _STREAMS.get(key)
    if stream is None:
        stream = _STREAMS[key] = wp.stream_from_torch(torch_stream)
    return stream


# the kernel-side array struct (array_t), taken from a live array rather than a private module path
_ARRAY_STRUCT = type(wp.zeros(1, dtype=wp.float32, device="cpu").__ctype__())


def _array_ctype(tensor):
    """The kernel-side array struct of a torch tensor (or `Vectors`), built from its pointer, shape and strides
    (bytes)."""
    if isinstance(tensor, Vectors):
        tensor = tensor.tensor
        item = tensor.element_size()
        return _ARRAY_STRUCT(data=tensor.data_ptr(), grad=0, ndim=tensor.dim() - 1, shape=tuple(tensor.shape[:-1]),
                             strides=tuple(stride * item for stride in tensor.stride()[:-1]))
    item = tensor.element_size()
    return _ARRAY_STRUCT(data=tensor.data_ptr(), grad=0, ndim=tensor.dim(), shape=tuple(tensor.shape),
                         strides=tuple(stride * item for stride in tensor.stride()))


def launch(kernel, dim: int | Sequence[int], inputs: Sequence, device: torch.device, block_dim: int = 0,
           threads_per_block: int = 256) -> None:
    """Launch a Warp kernel on ``device`` (torch's current stream on CUDA); ``block_dim`` > 0: a tiled launch
    (`wp.launch_tiled`: ``dim`` blocks of ``block_dim`` threads, the tile functions' block); otherwise ``dim``
    threads in blocks of ``threads_per_block`` (Warp's default 256; fewer lets a kernel of many registers a thread
    keep more warps on each multiprocessor).

    The first launch for a (kernel, device, dim, argument types) signature goes through `wp.launch` (overload
    resolution, from_torch wrapping) and is recorded; later ones replay the recorded launch with the new tensors'
    pointers written straight into its parameter block, which removes most of the per-call host overhead.
    """
    if isinstance(dim, int):
        dim = (dim,)
    dim = tuple(dim)
    if any(d == 0 for d in dim):
        return
    signature = tuple((x.dtype, x.dim()) if isinstance(x, torch.Tensor) else
                      x.signature if isinstance(x, Vectors) else type(x) for x in inputs)
    key = (kernel, device, dim, signature, block_dim, threads_per_block)
    recorded = _LAUNCH_CACHE.get(key)
    if recorded is None:
        arguments = [to_warp(x) if isinstance(x, (torch.Tensor, Vectors)) else x for x in inputs]
        if block_dim:
            command = wp.launch_tiled(kernel, dim=dim, inputs=arguments, device=wp.device_from_torch(device),
                                      block_dim=block_dim, record_cmd=True)
        else:
            command = wp.launch(kernel, dim=dim, inputs=arguments, device=wp.device_from_torch(device),
                                block_dim=threads_per_block, record_cmd=True)
        command.fwd_args = None  # drop the first call's arrays: a cached launch must not keep tensors alive
        recorded = _LAUNCH_CACHE[key] = _Recorded(command, [None] * len(inputs))
        if len(_LAUNCH_CACHE) > _LAUNCH_CACHE_SIZE:
            _LAUNCH_CACHE.popitem(last=False)
    else:
        _LAUNCH_CACHE.move_to_end(key)
    command, held = recorded.command, recorded.held
    for index, value in enumerate(inputs):
        if isinstance(value, (torch.Tensor, Vectors)):
            tensor = value.tensor if isinstance(value, Vectors) else value
            # a parameter already holding this pointer, shape and strides is left as it is (at batch 1 the caching
            # allocator hands out the same blocks call after call: building the struct is most of the host time)
            what = (tensor.data_ptr(), tensor.shape, tensor.stride())
            if held[index] != what:
                command.set_param_at_index_from_ctype(index, _array_ctype(value))
                held[index] = what
        elif held[index] != (type(value), value):
            command.set_param_at_index(index, value)
            held[index] = (type(value), value)
    command.launch(stream=_warp_stream(device) if device.type == "cuda" else None)


class _Recorded:
    """A recorded launch (`wp.Launch`) and what its parameters hold now: (pointer, shape, strides) for an array,
    (type, value) for a scalar."""

    __slots__ = ("command", "held")

    def __init__(self, command, held: list):
        self.command = command
        self.held = held


def reduction_lanes(total: int, device: torch.device) -> int:
    """Number of lanes for strided reductions: enough to fill a GPU, few on the (serial) CPU backend."""
    return max(1, min(total, 65536 if device.type == "cuda" else 64))


def seed_int32(seed: int) -> int:
    """Map any Python int to the int32 Warp's generator takes."""
    seed = int(seed) & 0xFFFFFFFF
    return seed - (1 << 32) if seed >= (1 << 31) else seed
