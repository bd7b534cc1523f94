"""One optimisation step of co-design training: forward (camera -> network) and loss, optionally compiled, backward,
camera-gradient throttling, learning-rate schedule and optimizer step, with the statistics kept on the device; on
CUDA the whole step can be captured once per phase as a CUDA graph and replayed."""

from __future__ import annotations

import contextlib
import math
import time

import torch

from warpsense.choices import COMPILE_MODES, SELF_CAPTURING_COMPILE_MODES
from warpsense.data.color import to_radiance
from warpsense.errors import first_line
from warpsense.train.losses import distillation_loss, segmentation_loss

EAGER_STEPS_BEFORE_CAPTURE = 3  # side-stream steps that initialise optimizer state, cuDNN and `auto` choices
# with DDP: torch's CUDA-graph notes ask for at least 11 DDP-enabled eager iterations before a capture (the reducer
# rebuilds its buckets after the first and samples run-time statistics with host reads in its early iterations)
DDP_EAGER_STEPS_BEFORE_CAPTURE = 11
LOSS_PARTS = ("ohem", "lovasz", "smooth", "distill")
STATISTICS = ("loss", *LOSS_PARTS, "steps", "nonfinite_steps")


def cosine_scale(step: int, total_steps: int) -> float:
    """Learning-rate multiplier of the cosine schedule: 1 at step 0, 0 at ``total_steps``."""
    return 0.5 * (1 + math.cos(math.pi * min(step, total_steps) / max(total_steps, 1)))


class TrainingStep:
    """Runs training steps and accumulates their statistics without a host synchronisation.

    Args:
        loss_config: the [loss] config section.
        optimizer: its param groups' initial ``lr`` are the base rates of the cosine schedule.
        camera_params: the learnable camera parameters (their gradient norm is clipped to ``camera_grad_clip``
            in the joint phase; 0 = no clip).
        total_steps: length of the cosine schedule.
        amp: bf16 autocast for the network.
        compile_mode: "off" or a `torch.compile` mode for the forward and loss (the backward is compiled with
            it); shapes are fixed by the training crop, so the step compiles once per phase.
        cuda_graph: capture forward, loss, backward, clipping, optimizer step and statistics as one CUDA graph per
            phase and batch shape, after `EAGER_STEPS_BEFORE_CAPTURE` eager steps, and replay it: no host work
            or kernel-launch overhead per step. The optimizer's learning rates become device tensors (the
            schedule writes them before each replay) and its steps capturable. Everything the step reads must
            keep its storage between steps (parameters, buffers, the optics' PSF cache do).
        micro_batch: > 0: run forward and backward on chunks of this many images and sum their gradients, each
            chunk's loss weighted by its share of the batch, before the one optimizer step: the peak memory of a
            chunk, the step of the whole batch (exactly so for losses that are means over images; OHEM picks its
            hardest pixels and batch norm its statistics within each chunk).
        teacher: a frozen model (`warpsense.system.build.load_teacher`) whose logits on the same images the
            network distils with weight ``loss_config.distill_weight`` (`distillation_loss`); it runs inside the
            step (compiled and captured with it) and is never part of the trained model.
        data_parallel: the model is DDP-wrapped (several ranks). With ``cuda_graph`` the gradient all-reduce (NCCL)
            is captured inside the step: the wrapper must be built within `capture_stream` (the side stream that
            warms up and captures), `DDP_EAGER_STEPS_BEFORE_CAPTURE` eager steps run first, and the capture is
            thread-local so that the process group's watchdog thread may query its events meanwhile.
        radiance_jitter: a `warpsense.data.photometric.RadianceJitter` applied to the batch's linear radiance before
            the camera (and the teacher: both read the same jittered scene), inside the step.
    """

    def __init__(self, loss_config, optimizer: torch.optim.Optimizer, camera_params: list, total_steps: int,
                 amp: bool, camera_grad_clip: float = 0.0, compile_mode: str = "off", cuda_graph: bool = False,
                 micro_batch: int = 0, teacher: torch.nn.Module | None = None, data_parallel: bool = False,
                 radiance_jitter: torch.nn.Module | None = None):
        if compile_mode not in COMPILE_MODES:
            raise ValueError(f"compile mode must be one of {COMPILE_MODES}, got {compile_mode!r}")
        if cuda_graph and compile_mode in SELF_CAPTURING_COMPILE_MODES:
            raise ValueError(f"train.cuda_graph captures the whole step; compile mode {compile_mode!r} captures "
                             "graphs itself: use compile = \"off\" or \"default\" with it")
        self.loss_config = loss_config
        self.optimizer = optimizer
        self.camera_params = camera_params
        self.total_steps = total_steps
        self.amp = amp
        self.camera_grad_clip = camera_grad_clip
        self.micro_batch = micro_batch
        self.teacher = teacher if loss_config.distill_weight > 0 else None
        self.radiance_jitter = radiance_jitter
        self.base_lrs = [float(group["lr"]) for group in optimizer.param_groups]
        self.compiled = compile_mode != "off"
        self.forward_loss = self._forward_loss if not self.compiled else \
            torch.compile(self._forward_loss, mode=None if compile_mode == "default" else compile_mode)
        self._phase: bool | None = None  # `joint` of the last step
        self._sums: torch.Tensor | None = None  # float64 [len(STATISTICS)] on the device, updated in place
        self._steps_since_read = 0
        self.cuda_graph = cuda_graph
        # the phase and batch shape being captured, eager steps run for it so far, and its graph once recorded
        self._capture_key, self._eager_count, self._captured = None, 0, None
        self._capture_seconds = 0.0
        self._eager_before_capture = DDP_EAGER_STEPS_BEFORE_CAPTURE if data_parallel else EAGER_STEPS_BEFORE_CAPTURE
        self._capture_mode = "thread_local" if data_parallel else "global"
        self._stream = None  # the one side stream of the warm-up steps and the captures (and a DDP wrapper's birth)
        if cuda_graph:
            device = optimizer.param_groups[0]["params"][0].device
            if device.type != "cuda":
                raise ValueError(f"train.cuda_graph needs a CUDA device; the model is on {device} (set "
                                 "train.cuda_graph=false)")
            self._stream = torch.cuda.Stream(device)
            for group in optimizer.param_groups:
                group["lr"] = torch.tensor(float(group["lr"]), device=device)
                group["capturable"] = True

    def _forward_loss(self, model, images, labels):
        if self.radiance_jitter is not None:  # float radiance passes the model's sRGB decoding as it is
            images = self.radiance_jitter(to_radiance(images))
        logits, sensed = model(images, self.amp)
        loss, parts = segmentation_loss(logits, labels, sensed, self.loss_config)
        if self.teacher is not None:
            with torch.no_grad():
                teacher_logits, _ = self.teacher(images, self.amp)
            parts["distill"] = distillation_loss(logits, teacher_logits, self.loss_config.distill_temperature,
                                                 self.loss_config.distill_mode)
            loss = loss + self.loss_config.distill_weight * parts["distill"].to(loss.dtype)
            parts["distill"] = parts["distill"].detach()
        return loss, parts

    def __call__(self, model, images: torch.Tensor, labels: torch.Tensor, step: int, joint: bool) -> None:
        """One step at schedule position ``step``; ``joint``: camera gradients are applied (and clipped)."""
        scale = cosine_scale(step, self.total_steps)
        for group, base_lr in zip(self.optimizer.param_groups, self.base_lrs):
            if torch.is_tensor(group["lr"]):
                group["lr"].fill_(base_lr * scale)
            else:
                group["lr"] = base_lr * scale
        self._steps_since_read += 1
        if self.compiled and self._phase is not None and joint != self._phase:
            # The phase switch flips requires_grad on camera parameters in place. Dynamo's guards can miss that and
            # replay the previous phase's graph, in which the camera takes no gradient (pytorch#139476; fixed after
            # torch 2.11 by pytorch#177158): a camera with a fixed lens would never learn. Recompile.
            torch.compiler.reset()
        self._phase = joint
        if not self.cuda_graph:
            self._eager_step(model, images, labels, joint)
            return
        key = (joint, tuple(images.shape), images.dtype, tuple(labels.shape), labels.dtype)
        if self._capture_key != key:  # a new phase or shape: the old graph (and its memory) goes
            self.release_graphs()
            self._capture_key = key
        if self._captured is None:
            if self._eager_count < self._eager_before_capture:
                self._eager_count += 1
                with self.capture_stream():  # warm-up must not run on the default stream (torch.cuda.graphs' recipe)
                    self._eager_step(model, images, labels, joint)
                return
            self._captured = self._capture(model, images, labels, joint)
        self._captured.images.copy_(images)
        self._captured.labels.copy_(labels)
        self._captured.graph.replay()

    def _eager_step(self, model, images, labels, joint) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        self._forward_backward_update(model, images, labels, joint)

    def _forward_backward_update(self, model, images, labels, joint) -> None:
        batch = images.shape[0]
        size = self.micro_batch if 0 < self.micro_batch < batch else batch
        if size == batch:
            loss, parts = self.forward_loss(model, images, labels)
            loss.backward()
        else:
            loss, parts = 0.0, {}
            for start in range(0, batch, size):
                share = min(size, batch - start) / batch
                part_loss, part_parts = self.forward_loss(model, images[start : start + size],
                                                          labels[start : start + size])
                (part_loss * share).backward()
                loss = loss + part_loss.detach() * share
                parts = {name: parts.get(name, 0.0) + value.detach() * share for name, value in part_parts.items()}
        if joint and self.camera_grad_clip > 0:
            trainable = [p for p in self.camera_params if p.grad is not None]
            if trainable:
                torch.nn.utils.clip_grad_norm_(trainable, self.camera_grad_clip)
        self.optimizer.step()
        self._accumulate(loss.detach(), parts)

    @contextlib.contextmanager
    def capture_stream(self):
        """Run the block on the side stream that warms up and captures the step, ordered after the work queued so
        far and before the work that follows (without ``cuda_graph``: on the current stream). A DDP wrapper of a
        captured step is built here (torch's CUDA-graph notes: DDP constructed on a side stream)."""
        if self._stream is None:
            yield
            return
        self._stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(self._stream):
            yield
        torch.cuda.current_stream().wait_stream(self._stream)

    def _capture(self, model, images, labels, joint) -> "_CapturedStep":
        """Record one step on static copies of the batch; it is not executed: the caller replays it."""
        static_images, static_labels = images.clone(), labels.clone()
        self.optimizer.zero_grad(set_to_none=True)  # gradients are then allocated (and overwritten) by the graph
        graph = torch.cuda.CUDAGraph()
        torch.cuda.synchronize()
        started = time.perf_counter()
        try:
            with torch.cuda.graph(graph, stream=self._stream, capture_error_mode=self._capture_mode):
                self._forward_backward_update(model, static_images, static_labels, joint)
        except RuntimeError as error:  # a host read or synchronisation inside the step: name it, not the CUDA code
            raise RuntimeError(f"train.cuda_graph: the training step could not be captured ({first_line(error)}); "
                               "run with train.cuda_graph=false") from error
        torch.cuda.synchronize()
        self._capture_seconds += time.perf_counter() - started
        return _CapturedStep(graph, static_images, static_labels)

    def release_graphs(self) -> None:
        """Free the captured step (its CUDA graph and memory pool); the next step warms up and captures anew.
        Call it before a process group is destroyed: NCCL cannot destroy a communicator while a graph that captured
        its all-reduce lives, and destroy_process_group then waits forever (pytorch#115388).
        Dropping the last reference is not enough: this object refers to itself (``forward_loss`` is its bound
        method), so it lives until the garbage collector runs."""
        if self._captured is not None:
            self._captured.graph.reset()
        self._capture_key, self._eager_count, self._captured = None, 0, None

    def take_capture_seconds(self) -> float:
        """Host seconds spent capturing CUDA graphs since the last call (0 without train.cuda_graph): part of the
        first epoch of each phase, reported apart so that a run's start-up time can be attributed."""
        seconds, self._capture_seconds = self._capture_seconds, 0.0
        return seconds

    @property
    def totals(self) -> dict[str, torch.Tensor]:
        """Sums since the last `epoch_statistics`, by name (``STATISTICS``)."""
        return dict(zip(STATISTICS, self._sums)) if self._steps_since_read else {}

    def _accumulate(self, loss: torch.Tensor, parts: dict) -> None:
        values = torch.stack([loss, *(parts.get(name, torch.zeros_like(loss)) for name in LOSS_PARTS)]).double()
        nonfinite = (~torch.isfinite(loss)).double()
        # a non-finite loss is counted, not summed: the epoch's mean stays readable
        step = torch.cat([torch.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0),
                          torch.ones_like(nonfinite).view(1), nonfinite.view(1)])
        if self._sums is None:
            self._sums = torch.zeros_like(step)
        self._sums.add_(step)  # in place: a captured step adds into the same buffer on every replay

    def epoch_statistics(self, context) -> dict[str, float]:
        """Mean loss and parts over the steps since the last call (all ranks), and the count of non-finite losses;
        one host synchronisation."""
        if not self._steps_since_read:
            return {}
        totals = dict(zip(STATISTICS, context.all_reduce_sum(self._sums.clone()).tolist()))
        self._sums.zero_()
        self._steps_since_read = 0
        steps = max(totals.pop("steps"), 1.0)
        nonfinite = int(totals.pop("nonfinite_steps"))
        finite_steps = max(steps - nonfinite, 1.0)
        statistics = {f"train_{name}" if name != "loss" else "train_loss": value / finite_steps
                      for name, value in totals.items()}
        statistics["nonfinite_steps"] = nonfinite
        return statistics


class _CapturedStep:
    """A recorded training step and the static input buffers it reads."""

    def __init__(self, graph: torch.cuda.CUDAGraph, images: torch.Tensor, labels: torch.Tensor):
        self.graph, self.images, self.labels = graph, images, labels
