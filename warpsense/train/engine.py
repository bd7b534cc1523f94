"""Two-phase co-design training (paper Alg. 1): warm-up with a frozen camera, then joint training with throttled
camera gradients, CFA temperature annealing, AdamW + cosine schedule, checkpoints, resume, metrics and plots."""

from __future__ import annotations

import itertools
import sys
import time
from pathlib import Path
from typing import NamedTuple

import torch
from PIL import Image
from torch.utils.data import DataLoader, DistributedSampler
from tqdm import tqdm

from warpsense.camera.camera import set_finite_check
from warpsense.data import (
    HELDOUT_SPLIT,
    DatasetError,
    Frames,
    build_dataset,
    build_fold,
    build_training,
    evaluation_splits,
    fold_name,
    frame_sequences,
    holds_out_fold,
    labelled_sources,
)
from warpsense.data.on_device import DecodedDataset, DeviceBatches, dataset_megabytes
from warpsense.data.photometric import RadianceJitter
from warpsense.data.transforms import EpochSampler
from warpsense.errors import first_line
from warpsense.files import environment
from warpsense.models import count_parameters
from warpsense.system import build_system, check_config, load_teacher
from warpsense.system.checkpoint import CheckpointError, restore, save_checkpoint
from warpsense.train.distributed import DistributedContext, launch_rank, wrap_data_parallel
from warpsense.train.evaluate import evaluate
from warpsense.train.inputs import check_inputs, input_digests
from warpsense.train.reproducibility import deterministic_algorithms
from warpsense.train.run_dir import (
    RunDir,
    fresh_run_dir,
    newest_run,
    resumed_config,
    superseded_name,  # noqa: F401 - under this module too, for older callers
)
from warpsense.train.schedule import Schedule
from warpsense.train.step import TrainingStep

# the run folder's names under this module, for callers written before `RunDir` (warpsense.study, the tests)
LAST, BEST, METRICS, EVALUATION = RunDir.LAST, RunDir.BEST, RunDir.METRICS, RunDir.EVALUATION


def _fit_time_budget(schedule: Schedule, budget_minutes: float, epoch_seconds: float, context) -> Schedule:
    """The plan shortened to fit ``budget_minutes``, judged from the first epoch; all ranks take rank 0's count."""
    fitted = torch.tensor([schedule.epochs_within(budget_minutes * 60, epoch_seconds)], dtype=torch.float64,
                          device=context.device)
    if context.enabled:
        torch.distributed.broadcast(fitted, src=0)
    shortened = schedule.shortened(int(fitted.item()))
    if shortened != schedule and context.is_main:
        print(f"time budget {budget_minutes} min: {schedule.epochs} -> {shortened.epochs} epochs "
              f"(warm-up {shortened.warmup_epochs})", flush=True)
    expected_minutes = shortened.epochs * epoch_seconds * 1.1 / 60
    if expected_minutes > budget_minutes and context.is_main:  # the shortest plan (2 epochs) does not fit either
        print(f"warning: time budget {budget_minutes:g} min cannot be met: the first epoch took "
              f"{epoch_seconds / 60:.1f} min, so the shortest plan ({shortened.epochs} epochs) needs about "
              f"{expected_minutes:.0f} min; stop it with Ctrl-C (it resumes) or use a smaller setting",
              file=sys.stderr, flush=True)
    return shortened


def _resumed_schedule(state: dict, requested: Schedule, checkpoint: Path) -> Schedule:
    """The plan a resumed run continues: the one saved in its checkpoint (a time budget may have shortened it),
    unless the resumed config requests another plan (``--allow-config-change``)."""
    saved = state.get("schedule")  # absent from checkpoints written before schedules were recorded
    if not isinstance(saved, dict) or saved.get("requested") != [requested.epochs, requested.warmup_epochs]:
        return requested
    epochs, warmup_epochs = saved.get("epochs"), saved.get("warmup_epochs")
    if not (isinstance(epochs, int) and isinstance(warmup_epochs, int) and 0 <= warmup_epochs <= epochs):
        raise CheckpointError(f"{checkpoint}: state.schedule must hold epochs >= warmup_epochs >= 0, got {saved!r}")
    return Schedule(epochs, warmup_epochs)


def _check_finite(model, statistics: dict, epoch: int, run_dir: Path) -> None:
    """Stop a diverged run before it writes a checkpoint: a non-finite loss or parameter raises."""
    names, parameters = zip(*model.named_parameters())
    finite = torch.stack([torch.isfinite(p).all() for p in parameters]).tolist()  # one host sync
    bad = [name for name, ok in zip(names, finite) if not ok]
    nonfinite_steps = statistics.get("nonfinite_steps", 0)
    if nonfinite_steps or bad:
        where = f"{nonfinite_steps} step(s) with a non-finite loss" if nonfinite_steps else \
            f"non-finite parameters ({', '.join(bad[:3])})"
        raise FloatingPointError(f"training diverged in epoch {epoch + 1}: {where}; stopped without saving this epoch "
                                 f"(the last checkpoint in {run_dir} is from before it); lower train.lr or check "
                                 f"the inputs")


def build_train_batches(config, train_set, context, progress: bool = True):
    """The training batches: on the GPU (`DeviceBatches`) when ``data.on_device`` allows and the decoded set fits
    in ``data.on_device_max_mb``, else a DataLoader (workers decode and augment on the CPU). Both have
    ``set_epoch``, ``len`` and iterate (uint8 images [B, 3, h, w], int64 labels [B, h, w])."""
    device = context.device
    per_rank = config.data.batch_size // context.world_size
    crop = (config.data.crop_height, config.data.crop_width)
    on_device = config.data.on_device == "always" or (
        config.data.on_device == "auto" and device.type == "cuda"
        and dataset_megabytes(train_set.dataset) <= config.data.on_device_max_mb)
    if on_device:
        return DeviceBatches(train_set.dataset, device, per_rank, crop, (config.data.scale_min, config.data.scale_max),
                             config.data.hflip, config.run.seed, context.rank, context.world_size,
                             progress and context.is_main, config.data.scale_fill, train_set.paste_classes,
                             train_set.paste_probability)
    sampler = EpochSampler(DistributedSampler(train_set, num_replicas=context.world_size, rank=context.rank,
                                              shuffle=True, seed=config.run.seed, drop_last=True), len(train_set))
    loader = DataLoader(train_set, batch_size=per_rank, sampler=sampler, num_workers=config.data.num_workers,
                        drop_last=True, pin_memory=device.type == "cuda",
                        persistent_workers=config.data.num_workers > 0)
    loader.set_epoch = sampler.set_epoch
    return loader


def _ranked_batchnorm(model, config, ddp_on_cuda: bool):
    """With DDP on CUDA, BatchNorm becomes SyncBatchNorm unless ``train.sync_batchnorm`` is false (its per-layer
    all-gather is latency a small network pays on every step; each rank then uses its own share of the batch)."""
    if ddp_on_cuda and config.train.sync_batchnorm:
        return torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
    return model


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C during training; ``run_dir`` holds the last completed epoch's checkpoint."""

    def __init__(self, run_dir: Path):
        super().__init__(str(run_dir))
        self.run_dir = run_dir


def train(config, resume: str | Path | bool = False, progress: bool = True, return_model: bool = False,
          allow_config_change: bool = False):
    """Train ``config`` and return the run directory.

    Args:
        config: a resolved `warpsense.config.Config`; None when resuming to continue with the run's own config.
        resume: False for a new run (a fresh directory <output_dir>/<name>[-N]); True to continue the newest run
            <output_dir>/<name>[-N]; or a run directory path. Resuming restores the run's config (`RunDir.CONFIG`),
            weights, optimizer, RNG and epoch from the last checkpoint (written atomically at every epoch end), so
            at most the interrupted epoch is redone. A ``config`` that differs from the run's is refused unless
            ``allow_config_change``.
        progress: show tqdm progress bars (rank 0 only).
        return_model: also return the trained SensingModel (this rank's copy): (run_dir, model); the model is None
            when ``resume`` names a finished run (nothing trains).

    Raises:
        TrainingInterrupted: on Ctrl-C, naming the run directory to resume.
    """
    if resume:
        run_dir = Path(resume) if not isinstance(resume, bool) else newest_run(config.run.output_dir, config.run.name)
        run = RunDir(run_dir)
        if not run.resumable():
            raise FileNotFoundError(f"{run_dir}: no {run.LAST} to resume from")
        config = resumed_config(run_dir, config, allow_config_change)
        check_config(config, f"{run.config}")
        finished = _finished_epochs(run, config)
        if finished:
            if launch_rank() == 0:  # no process group yet: one line from torchrun's rank 0, not one a rank
                print(f"{run_dir}: already finished ({finished[0]} of {finished[1]} epochs); nothing to resume "
                      "(--extend N trains N more)")
            return (run_dir, None) if return_model else run_dir
        check_inputs(run_dir, config)  # the files it read, by content: a changed class table is another task
    elif config is None:
        raise ValueError("train: a config is needed for a new run")
    else:
        check_config(config, f"config {config.run.name}")
        run_dir = fresh_run_dir(Path(config.run.output_dir) / config.run.name)
        run = RunDir(run_dir)
    context = DistributedContext.from_environment(config.run.device)
    lock = run.lock()
    # the outermost folder this call creates (the run's, or an output_dir above it): removed if no epoch completes
    created = next((folder for folder in (*reversed(run_dir.parents), run_dir) if not folder.exists()), None) \
        if context.is_main else None
    if context.is_main:
        try:
            run_dir.mkdir(parents=True, exist_ok=True)
        except OSError as error:  # e.g. a folder under /proc, or one another user owns: name the key, not errno
            run.remove_unfinished(created)  # the output folders made above it
            raise ValueError(f"run.output_dir {config.run.output_dir}: cannot create the run folder {run_dir} "
                             f"({error.strerror})") from None
        lock.acquire()
    try:
        with deterministic_algorithms(config.run.deterministic):
            return _train(config, run_dir, bool(resume), context, progress, return_model)
    except KeyboardInterrupt:
        run.remove_unfinished(created)
        raise TrainingInterrupted(run_dir) from None
    except Exception:
        run.remove_unfinished(created)
        raise
    finally:
        lock.release()


def _finished_epochs(run: RunDir, config) -> tuple[int, int] | None:
    """(epochs trained, epochs planned) of a run with nothing left to resume: its last checkpoint holds every epoch
    of its plan (the saved one, or the one ``config`` changes it to) and its final evaluation is written; None
    otherwise (a run stopped after its last epoch but before that evaluation resumes to write it)."""
    if not run.finished():
        return None
    _, state = run.read_resume_point()
    schedule = _resumed_schedule(state, Schedule.from_config(config.train), run.last)
    trained = state["epoch"] + 1
    return (trained, schedule.epochs) if trained >= schedule.epochs else None


class _Datasets(NamedTuple):
    train: object
    val: object
    selection: object | None  # training images held out by prefix (model selection), or None: select on val


def _datasets(config) -> _Datasets:
    seed = config.run.seed
    train = build_training(config.data, seed)
    if holds_out_fold(config.data):  # a fold: validate (and judge) on its held-out frames
        return _Datasets(train, build_fold(config.data, train=False, seed=seed), None)
    return _Datasets(
        train,
        build_dataset(config.data, config.data.val_split, train=False, seed=seed),
        build_dataset(config.data, config.data.train_split, train=False, seed=seed, part="holdout")
        if config.data.holdout_prefix else None)


def _evaluation_files(dataset) -> list[Path]:
    """The image and label files an evaluation set reads (none for generated scenes)."""
    if isinstance(dataset, Frames):  # a sequence fold: chosen frames of the labelled splits
        pairs = [getattr(source, "pairs", None) for source in dataset.sources]
        return [path for source, index in dataset.frames if pairs[source] for path in pairs[source][index]]
    return [path for pair in getattr(dataset, "pairs", ()) for path in pair]


def _check_evaluation_files(datasets: _Datasets, config) -> None:
    """Stop before the first epoch on an unreadable image or label of a set the run evaluates (val or the
    held-out sequence, the held-out prefix, the final evaluation's other splits): they are read only at the first
    evaluation, after epochs are spent (training images are read in the first epoch, before any checkpoint). PIL's
    verify reads the file's header and chunk checksums without decoding it, a fraction of a decode's time."""
    val_name = f"held-out {fold_name(config.data)}" if holds_out_fold(config.data) else config.data.val_split
    checked = [(val_name, datasets.val), (f"held-out prefix {config.data.holdout_prefix}", datasets.selection)]
    checked += [(split, build_dataset(config.data, split, train=False, seed=config.run.seed))
                for split in evaluation_splits(config.data) if split not in (config.data.val_split, HELDOUT_SPLIT)]
    for name, dataset in checked:
        for path in _evaluation_files(dataset):
            try:
                with Image.open(path) as image:
                    image.verify()
            except (OSError, SyntaxError) as error:  # PIL reports a broken PNG chunk as a SyntaxError
                raise DatasetError(f"{path}: unreadable image of the {name} set ({first_line(error)})") from None


def _optimizer(config, model, device) -> torch.optim.AdamW:
    """AdamW with two groups: the network (weight decay) and the learnable camera parameters (``lr`` scaled by
    ``train.camera_lr_scale``, no decay); frozen camera parameters are left out."""
    camera_params = model.camera.learnable_parameters()
    camera_ids = {id(p) for p in camera_params}
    network_params = [p for p in model.parameters() if id(p) not in camera_ids and p.requires_grad]
    return torch.optim.AdamW([
        {"params": network_params, "lr": config.train.lr, "weight_decay": config.train.weight_decay},
        {"params": camera_params, "lr": config.train.lr * config.train.camera_lr_scale, "weight_decay": 0.0},
    ], fused=device.type == "cuda")


def every(epoch: int, interval: int, epochs: int) -> bool:
    """Whether 0-based ``epoch`` of ``epochs`` is one of every ``interval``-th and the last (validation's
    ``train.eval_every``, the resume point's ``train.checkpoint_every``)."""
    return (epoch + 1) % interval == 0 or epoch == epochs - 1


def eval_batch_size(config) -> int:
    """Images per evaluation batch: ``train.eval_batch_size``, or the training batch when it is 0."""
    return config.train.eval_batch_size or config.data.batch_size


def _validate(model, datasets: _Datasets, config, context, amp: bool, progress: bool) -> dict:
    """Validation metrics of one epoch (and the held-out selection set's, when there is one)."""
    evaluation = dict(device=context.device, batch_size=eval_batch_size(config), context=context,
                      class_names=datasets.train.classes, amp=amp, progress=progress and context.is_main)
    metrics = evaluate(model, datasets.val, **evaluation)
    record = {"val_miou": metrics["miou"], "val_pixel_accuracy": metrics["pixel_accuracy"],
              "val_per_class_iou": metrics["per_class_iou"]}
    if datasets.selection is not None:
        selection = evaluate(model, datasets.selection, **evaluation)
        record.update({"selection_miou": selection["miou"], "selection_per_class_iou": selection["per_class_iou"]})
    return record


def _run_epoch(training_step, model, batches, steps: int, step: int, joint: bool, device, bar) -> int:
    """Train ``steps`` batches from ``batches`` (a ``bar`` ticks per step, closed at the end); the next step index."""
    for images, labels in itertools.islice(batches, steps):
        training_step(model, images.to(device, non_blocking=True), labels.to(device, non_blocking=True), step, joint)
        step += 1
        bar.update(1)
    bar.close()
    return step


def _write_epoch(run_dir: Path, model, optimizer, config, state: dict, is_best: bool, is_resume_point: bool) -> None:
    """Append the epoch's record to the run's metrics, then write the checkpoints: the best one when the epoch scored
    best, and the last one (with optimizer and RNG state, for resuming) when the epoch is a resume point
    (``train.checkpoint_every``; a resume drops the records after it)."""
    run = RunDir(run_dir)
    run.append_metrics(state["record"])
    if is_best:
        save_checkpoint(run.best, model, config.to_dict(), state)
    if is_resume_point:
        save_checkpoint(run.last, model, config.to_dict(), state, optimizer, torch.get_rng_state())


def _epoch_line(record: dict, schedule: Schedule, config) -> str:
    miou = f"{record['val_miou']:.4f}" if "val_miou" in record else "-"
    if "selection_miou" in record:
        miou += f" (held-out {config.data.holdout_prefix}: {record['selection_miou']:.4f})"
    judged = f"held-out {fold_name(config.data)}" if holds_out_fold(config.data) else "val"
    return (f"epoch {record['epoch'] + 1}/{schedule.epochs} {record['phase']}: loss {record['train_loss']:.4f} "
            f"{judged} mIoU {miou} ({record['images_per_s']:.1f} img/s)")


def _train(config, run_dir: Path, resume: bool, context, progress: bool, return_model: bool):
    run = RunDir(run_dir)
    run_started = time.perf_counter()
    device = context.device
    torch.manual_seed(config.run.seed)
    inputs = input_digests(config) if context.is_main else None  # before the files are read
    datasets = _datasets(config)
    _check_evaluation_files(datasets, config)
    num_classes = config.model.num_classes or len(datasets.train.classes)
    model = build_system(config, num_classes).to(device)
    set_finite_check(model, False)  # 8-bit inputs; the loss and parameters are checked each epoch (_check_finite)
    model = _ranked_batchnorm(model, config, context.enabled and device.type == "cuda")
    optimizer = _optimizer(config, model, device)
    if config.data.batch_size % context.world_size:
        raise ValueError(f"data.batch_size={config.data.batch_size} must be divisible by {context.world_size} ranks")
    loader = build_train_batches(config, datasets.train, context, progress)
    if isinstance(loader, DeviceBatches):  # the evaluation sets join the training set on the device
        datasets = _Datasets(datasets.train, *(
            DecodedDataset(split, device, progress and context.is_main)
            if split is not None and dataset_megabytes(split) <= config.data.on_device_max_mb else split
            for split in (datasets.val, datasets.selection)))
    steps_per_epoch = min(len(loader), config.train.max_steps_per_epoch or len(loader))
    if steps_per_epoch == 0:
        raise ValueError(f"training set of {len(datasets.train)} images gives no batch of {config.data.batch_size}")
    data_s = time.perf_counter() - run_started  # datasets, the training batches, decoding onto the device
    amp = config.train.amp and device.type == "cuda"

    requested = schedule = Schedule.from_config(config.train)
    if resume:
        tensors, state = run.read_resume_point()
        restore(tensors, model, optimizer, source=run.last)
        start_epoch, step, best_miou = state["epoch"] + 1, state["step"], state["best_miou"]
        best_miou = max(best_miou, run.kept_best())
        schedule = _resumed_schedule(state, requested, run.last)
        torch.set_rng_state(tensors["rng"])
        history = run.read_metrics(state["epoch"])
        if context.is_main:
            print(f"resuming {run_dir} from epoch {start_epoch + 1}/{schedule.epochs}" if start_epoch < schedule.epochs
                  else f"resuming {run_dir}: all {schedule.epochs} epochs trained; writing its final evaluation")
    else:
        start_epoch, step, best_miou, history = 0, 0, -1.0, []
        # each rank draws its own noise seeds from here on (parameters stay identical: DDP syncs gradients)
        torch.manual_seed(config.run.seed * 1000 + context.rank + 1)
    if context.is_main:
        versions = environment()
        if not resume:  # a continuation's own files wait for its first complete epoch (`RunDir.write_run_files`)
            run.write_run_files(config, versions, history, inputs=inputs)
        print(f"run directory: {run_dir}")
        camera_parameters = sum(p.numel() for p in model.camera.learnable_parameters())
        print(f"network parameters: {count_parameters(model.network):,}; camera parameters: "
              f"{camera_parameters:,}; device: {device}; ranks: {context.world_size}")

    teacher = None
    if config.loss.distill_weight > 0:  # read for training only: the checkpoint keeps the student alone
        teacher = load_teacher(config.loss.teacher, num_classes, device)
        if context.is_main:
            print(f"distilling {config.loss.teacher} ({count_parameters(teacher.network):,} parameters), weight "
                  f"{config.loss.distill_weight}, T = {config.loss.distill_temperature}, "
                  f"{config.loss.distill_mode}-wise")
    training_step = TrainingStep(config.loss, optimizer, model.camera.learnable_parameters(),
                                 schedule.epochs * steps_per_epoch, amp, config.train.camera_grad_clip,
                                 config.train.compile, config.train.cuda_graph,
                                 config.train.micro_batch, teacher, data_parallel=context.enabled,
                                 radiance_jitter=RadianceJitter.from_config(config.data))
    wrapped, wrapped_phase = model, None
    epoch = start_epoch
    # where a run's time goes before its first step (the first epoch's own time includes the compile / graph capture)
    setup = {"setup_s": time.perf_counter() - run_started, "setup_data_s": data_s}
    while epoch < schedule.epochs:  # a while loop: the time budget may shorten the schedule after the first epoch
        joint = schedule.is_joint(epoch)
        model.camera.on_epoch(schedule, epoch)  # the joint phase trains the camera; the CFA anneals
        if context.enabled and wrapped_phase != joint:  # DDP buckets the parameters that take gradients
            with training_step.capture_stream():  # a captured step captures DDP's all-reduce: built on its stream
                wrapped = wrap_data_parallel(model, device)
            wrapped_phase = joint
        loader.set_epoch(epoch)
        model.train()
        started = time.perf_counter()
        description = f"epoch {epoch + 1}/{schedule.epochs} ({schedule.phase(epoch)})"
        step = _run_epoch(training_step, wrapped, loader, steps_per_epoch, step, joint, device,
                          tqdm(total=steps_per_epoch, desc=description, disable=not (progress and context.is_main),
                               leave=False))
        statistics = training_step.epoch_statistics(context)
        elapsed = time.perf_counter() - started
        _check_finite(model, statistics, epoch, run_dir)
        if epoch == 0 and config.train.time_budget_minutes > 0:
            schedule = _fit_time_budget(schedule, config.train.time_budget_minutes, elapsed, context)
            training_step.total_steps = schedule.epochs * steps_per_epoch
        record = {
            "epoch": epoch, "step": step, "phase": schedule.phase(epoch),
            "lr": float(optimizer.param_groups[0]["lr"]), **statistics,
            "images_per_s": steps_per_epoch * config.data.batch_size / elapsed, "epoch_time_s": elapsed,
            **(setup if epoch == start_epoch else {}),
        }
        capture_s = training_step.take_capture_seconds()
        if capture_s:
            record["capture_s"] = capture_s  # of this epoch's time: the CUDA graph capture of a new phase
        if every(epoch, config.train.eval_every, schedule.epochs):
            record.update(_validate(model, datasets, config, context, amp, progress))
        # this process's time so far, setup and evaluation included
        record["wall_s"] = time.perf_counter() - run_started
        record.update(model.camera.summary())
        score = record.get("selection_miou", record.get("val_miou", -1.0))
        is_best = score > best_miou
        best_miou = max(best_miou, score)
        if context.is_main:
            if resume and epoch == start_epoch:
                run.supersede_final_files(start_epoch)  # first: a kill after it leaves an unfinished run
                run.write_run_files(config, versions, history, continued_from=start_epoch, inputs=inputs)
            state = {"epoch": epoch, "step": step, "best_miou": best_miou, "num_classes": num_classes,
                     "class_names": list(datasets.train.classes), "record": record, "environment": versions,
                     "schedule": {**schedule.to_dict(), "requested": [requested.epochs, requested.warmup_epochs]}}
            _write_epoch(run_dir, model, optimizer, config, state, is_best,
                         every(epoch, config.train.checkpoint_every, schedule.epochs))
            print(_epoch_line(record, schedule, config), flush=True)
        context.barrier()
        epoch += 1
    if context.is_main:
        final_evaluation(run, model, datasets, config, schedule.epochs - 1, num_classes, device, amp, progress)
    if context.is_main and config.train.plots:
        from warpsense.train.plots import write_run_plots

        write_run_plots(run_dir, model, datasets.val, device)
    if context.is_main:
        print(run_summary(run, config))
    # the DDP wrapper's reducer holds the process group: freed after destroy_process_group, gloo's destructor can
    # deadlock (seen on CPU, 1 run in ~3), so it goes first
    del wrapped
    training_step.release_graphs()  # a live graph holding NCCL's all-reduce makes destroy_process_group wait forever
    context.barrier()
    context.close()
    return (run_dir, model) if return_model else run_dir


def final_evaluation(run: RunDir, model, datasets: _Datasets, config, epoch: int, num_classes: int, device,
                     amp: bool, progress: bool = False) -> dict:
    """Judge the model as training left it (the final epoch) on every labelled split (`evaluation_splits`) and write
    `RunDir.EVALUATION`: per split mIoU, pixel accuracy, per-class IoU, each image's per-class (TP, FP, FN) pixel counts
    (what `warpsense study report` resamples) and the split's confusion matrix (which class the errors went to),
    with the camera's learned state; ``epoch``: the plan's last (0-based).
    Returns the record."""
    record = {"epoch": epoch,
              "class_names": list(datasets.train.classes), "num_classes": num_classes,
              "network_parameters": count_parameters(model.network), "camera": model.camera.summary(),
              "holdout_sequence": config.data.holdout_sequence, "fold": fold_name(config.data),
              "train_frames": len(datasets.train), "labelled_frames": _labelled_frames(config),
              "train_sequences": _sequences(getattr(datasets.train, "dataset", datasets.train)), "splits": {}}
    for split in evaluation_splits(config.data):
        dataset = datasets.val if split in (config.data.val_split, HELDOUT_SPLIT) else \
            build_dataset(config.data, split, train=False, seed=config.run.seed)
        metrics = evaluate(model, dataset, device, eval_batch_size(config),
                           class_names=datasets.train.classes, amp=amp, progress=progress, per_image=True)
        metrics["image_counts"] = metrics["image_counts"].tolist()
        metrics["image_sequences"] = _sequences(dataset, distinct=False)
        record["splits"][split] = metrics
    run.write_evaluation(record)
    return record


def _labelled_frames(config) -> int | None:
    """The frames of the labelled splits a fold is cut from (train_split + val_split), None without a fold."""
    return sum(len(source) for source in labelled_sources(config.data, config.run.seed)) \
        if holds_out_fold(config.data) else None


def _sequences(dataset, distinct: bool = True) -> list[str] | None:
    """The sequence of each frame of ``dataset`` (sorted distinct names with ``distinct``), None where its frames
    carry no sequence names: the report's clustered bootstrap and its note on val sharing drives with training."""
    try:
        names = frame_sequences(dataset)
    except DatasetError:
        return None
    return sorted(set(names)) if distinct else names


def run_summary(run: RunDir, config) -> str:
    """The closing lines of a run: the best checkpoint's score and epoch, and where everything went."""
    lines = [f"done: {run}"]
    try:
        best = run.best_record()
    except (OSError, ValueError, KeyError, TypeError) as error:  # the run is trained: name the damage, go on
        best = None
        lines.append(f"  best: {run.BEST} (its readable copy {run.best_copy} is damaged: {type(error).__name__}: "
                     f"{first_line(error)})")
    if best is not None:
        if "selection_miou" in best:
            score = (f"held-out {config.data.holdout_prefix} mIoU {best['selection_miou']:.4f}, "
                     f"val {best['val_miou']:.4f}")
        elif holds_out_fold(config.data):
            score = f"held-out {fold_name(config.data)} mIoU {best['val_miou']:.4f}"
        else:
            score = f"val mIoU {best['val_miou']:.4f}"
        lines.append(f"  best: {run.BEST} (epoch {best['epoch'] + 1}, {score})")
    lines.append(f"  last: {run.LAST}; metrics: {run.METRICS}; config: {run.CONFIG}"
                 + ("; plots: *.png" if config.train.plots else ""))
    return "\n".join(lines)
