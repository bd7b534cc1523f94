"""The training step: device-side statistics, the cosine schedule, camera gradient clipping, and a diverged run
stopped before it saves a checkpoint."""

import math

import pytest
import torch

from tests.conftest import device_params
from tests.train.test_training import TINY
from warpsense.camera import Camera
from warpsense.camera.geometry import cfa_flip, cfa_unflip
from warpsense.config import load_config
from warpsense.system import SensingModel, build_system, read_checkpoint
from warpsense.train import engine
from warpsense.train.distributed import DistributedContext
from warpsense.train.engine import train
from warpsense.train.schedule import Schedule
from warpsense.train.step import TrainingStep, cosine_scale


def _step_and_batch(overrides=()):
    config = load_config(None, ["noise.enabled=false", *overrides])
    torch.manual_seed(0)
    model = build_system(config, 11)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    images = torch.randint(0, 256, (2, 3, 16, 24), dtype=torch.uint8)
    labels = torch.randint(0, 11, (2, 16, 24))
    return config, model, optimizer, images, labels


def test_cosine_scale():
    assert cosine_scale(0, 10) == 1.0 and cosine_scale(10, 10) == pytest.approx(0.0)
    assert cosine_scale(5, 10) == pytest.approx(0.5) and cosine_scale(20, 10) == pytest.approx(0.0)


def test_statistics_are_the_mean_of_the_step_losses():
    config, model, optimizer, images, labels = _step_and_batch()
    step = TrainingStep(config.loss, optimizer, model.camera.learnable_parameters(), total_steps=4, amp=False)
    losses = []
    for index in range(3):
        before = [p.detach().clone() for p in model.network.parameters()]
        step(model, images, labels, index, joint=False)
        losses.append(float(step.totals["loss"]) - sum(losses))
        assert any(not torch.equal(a, b) for a, b in zip(before, model.network.parameters()))
    assert optimizer.param_groups[0]["lr"] == pytest.approx(1e-3 * cosine_scale(2, 4))
    statistics = step.epoch_statistics(DistributedContext())
    assert statistics["train_loss"] == pytest.approx(sum(losses) / 3) and statistics["nonfinite_steps"] == 0
    assert set(statistics) == {"train_loss", "train_ohem", "train_lovasz", "train_smooth", "train_distill",
                               "nonfinite_steps"}
    assert step.epoch_statistics(DistributedContext()) == {}  # reset after reading


def test_camera_gradient_is_clipped_in_the_joint_phase():
    config, model, optimizer, images, labels = _step_and_batch()
    clip = 1e-4
    step = TrainingStep(config.loss, optimizer, model.camera.learnable_parameters(), 4, False, camera_grad_clip=clip)
    step(model, images, labels, 0, joint=True)
    norm = math.sqrt(sum(float(p.grad.square().sum()) for p in model.camera.learnable_parameters()
                         if p.grad is not None))
    assert norm == pytest.approx(clip, rel=1e-4)


def test_non_finite_loss_is_counted():
    config, model, optimizer, images, labels = _step_and_batch()
    step = TrainingStep(config.loss, optimizer, model.camera.learnable_parameters(), 4, False)
    with torch.no_grad():
        next(model.network.parameters()).fill_(float("nan"))
    step(model, images, labels, 0, joint=False)
    statistics = step.epoch_statistics(DistributedContext())
    assert statistics["nonfinite_steps"] == 1 and math.isfinite(statistics["train_loss"])


def test_diverged_run_stops_before_saving(tmp_path, monkeypatch):
    """A NaN parameter after warm-up (as an infinite learning rate or a NaN lens coefficient gives) stops the run
    with a one-line error; the checkpoints on disk are from the last finite epoch."""
    config = load_config(None, TINY + ["train.epochs=3", "train.warmup_epochs=1", f"run.output_dir={tmp_path}"])
    original = TrainingStep.__call__

    def poisoned(self, model, images, labels, step, joint):
        if joint:
            with torch.no_grad():
                model.camera.exposure.gain_logit.fill_(float("nan"))
        return original(self, model, images, labels, step, joint)

    monkeypatch.setattr(TrainingStep, "__call__", poisoned)
    with pytest.raises(FloatingPointError, match="epoch 2"):
        train(config, progress=False)
    run = tmp_path / "default"
    state = read_checkpoint(run / engine.LAST)[1]["state"]
    assert state["epoch"] == 0 and math.isfinite(state["best_miou"])


def test_cfa_flip_keeps_every_pixel_on_its_site():
    """A scene of one colour captured through RGGB: the raw depends only on the site, so a phase-keeping mirror of it
    is itself (a plain flip of an even-width frame swaps R and G columns)."""
    from warpsense.ops import cfa_mosaic

    phi = torch.tensor([[[1.0, 0, 0], [0, 1, 0]], [[0, 1, 0], [0, 0, 1]]])
    for width in (8, 9):
        raw = cfa_mosaic(torch.tensor([0.9, 0.5, 0.1]).view(1, 3, 1, 1).expand(1, 3, 4, width).contiguous(), phi)
        mirrored, shift = cfa_flip(raw, 2)
        assert shift == (1 if width % 2 == 0 else 0)
        assert torch.equal(mirrored[..., shift:], raw[..., shift:])  # the repeated edge column aside
        assert not torch.equal(raw.flip(-1), raw) or width % 2
        ramp = torch.arange(width, dtype=torch.float32).expand(1, 1, 4, width)
        restored = cfa_unflip(cfa_flip(ramp, 2)[0], shift)  # an identity network
        assert torch.equal(restored[..., shift:], ramp[..., shift:])
    with pytest.raises(ValueError, match="2x2"):
        cfa_flip(raw, 3)


def test_flip_tta_eval_runs(tmp_path):
    config = load_config(None, TINY + ["train.epochs=1", "train.warmup_epochs=0", f"run.output_dir={tmp_path}"])
    run, model = train(config, progress=False, return_model=True)
    from warpsense.data import build_dataset
    from warpsense.train.evaluate import evaluate

    dataset = build_dataset(config.data, "val", train=False)
    assert evaluate(model, dataset, "cpu", flip=True)["num_images"] == len(dataset)
    model.eval()
    images = torch.stack([dataset[i][0] for i in range(2)])
    index = torch.arange(2)
    plain = model.probabilities(images, image_index=index)
    averaged = model.probabilities(images, image_index=index, flip=True)
    logits, sensed = model(images, image_index=index)
    mirrored, shift = cfa_flip(sensed, model.camera.tile)
    expected = 0.5 * (plain + cfa_unflip(torch.softmax(model.network(mirrored), dim=1), shift))
    torch.testing.assert_close(averaged, expected)
    assert not torch.allclose(averaged, plain)


def test_holdout_prefix_selects_on_a_sequence_training_never_sees(shared_data, tmp_path):
    from warpsense.data import build_dataset

    config = load_config("camvid_codesign", TINY + [f"data.root={shared_data / 'camvid'}", "data.holdout_prefix=0006R0",
                                                    "optics.enabled=false"])
    rest = build_dataset(config.data, "train", train=True, part="rest")
    held = build_dataset(config.data, "train", train=False, part="holdout")
    assert len(rest) + len(held) == 367 and len(held) == 101
    assert all(p[0].name.startswith("0006R0") for p in held.pairs)
    assert not any(p[0].name.startswith("0006R0") for p in rest.dataset.pairs)
    with pytest.raises(Exception, match="holdout prefix"):
        build_dataset(load_config(None, ["data.dataset=camvid", f"data.root={shared_data / 'camvid'}",
                                         "data.holdout_prefix=XYZ"]).data, "train", False, part="holdout")


def test_exception_cuda_graph_needs_cuda():
    config, model, optimizer, images, labels = _step_and_batch()
    with pytest.raises(ValueError, match="needs a CUDA device"):
        TrainingStep(config.loss, optimizer, model.camera.learnable_parameters(), 4, False, cuda_graph=True)


@pytest.mark.cuda
def test_cuda_graph_steps_match_eager_steps():
    """A captured-and-replayed step trains exactly like the eager one: the learnable-lens camera in both phases,
    a new batch every step, a changing learning rate, clipped camera gradients and device statistics. The network is
    a small deterministic one (DSUNet's upsampling backward uses atomics, so two of its eager runs differ already),
    cuDNN is set deterministic and the lens renders in float64, so the two runs agree to rounding. (With the
    float32 rendering the two differed by 2e-4 relative in one camera parameter on the H100, most likely because
    Adam divides by the root of near-zero lens gradients, which makes float32 rounding visible.)"""
    torch.backends.cudnn.deterministic, deterministic = True, torch.backends.cudnn.deterministic
    try:
        config = load_config("camvid_codesign", ["optics.render_precision=float64"])
        generator = torch.Generator().manual_seed(1)
        batches = [(torch.randint(0, 256, (2, 3, 32, 48), dtype=torch.uint8, generator=generator).cuda(),
                    torch.randint(0, 11, (2, 32, 48), generator=generator).cuda()) for _ in range(12)]
        results = []
        for cuda_graph in (False, True):
            torch.manual_seed(0)
            network = torch.nn.Sequential(torch.nn.Conv2d(1, 8, 3, padding=1), torch.nn.BatchNorm2d(8),
                                          torch.nn.ReLU(), torch.nn.Conv2d(8, 11, 3, padding=1))
            model = SensingModel(Camera.from_config(config), network).cuda().train()
            camera = model.camera.learnable_parameters()
            optimizer = torch.optim.AdamW([{"params": list(network.parameters()), "lr": 3e-3},
                                           {"params": camera, "lr": 1e-3}], fused=True)
            step = TrainingStep(config.loss, optimizer, camera, total_steps=12, amp=True, camera_grad_clip=0.5,
                                cuda_graph=cuda_graph)
            statistics = []
            for index, (images, labels) in enumerate(batches):
                joint = index >= 6
                if index in (0, 6):
                    model.camera.on_epoch(Schedule(2, 1), int(joint))  # epoch 1 of 2 is joint
                step(model, images, labels, index, joint)
                if index in (5, 11):
                    statistics.append(step.epoch_statistics(DistributedContext()))
            # two phases captured (or none): their host time is reported once, then reset
            assert (step.take_capture_seconds() > 0) == cuda_graph and step.take_capture_seconds() == 0
            results.append(([p.detach().clone() for p in model.parameters()], statistics))
        (eager, eager_statistics), (graphed, graphed_statistics) = results
        for a, b in zip(eager, graphed):
            torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)
        for a, b in zip(eager_statistics, graphed_statistics):
            assert b == pytest.approx(a, rel=1e-5)
    finally:
        torch.backends.cudnn.deterministic = deterministic


@pytest.mark.parametrize("device", device_params())
def test_compiled_step_trains_the_camera_after_warm_up(device):
    """Warm-up freezes the camera and the joint phase unfreezes it in place. A compiled step must then take the
    camera's gradients: torch 2.11's dynamo replayed the warm-up graph, and a camera with a fixed lens (exposure and
    CFA learnable) never moved in 100 CamVid epochs on the H100."""
    config = load_config("camvid_learned_cfa_exposure", ["optics.enabled=false"])
    torch.manual_seed(0)
    network = torch.nn.Sequential(torch.nn.Conv2d(1, 4, 3, padding=1), torch.nn.ReLU(), torch.nn.Conv2d(4, 11, 1))
    model = SensingModel(Camera.from_config(config), network).to(device).train()
    camera = model.camera.learnable_parameters()
    optimizer = torch.optim.AdamW([{"params": list(network.parameters())}, {"params": camera}], lr=1e-2)
    step = TrainingStep(config.loss, optimizer, camera, total_steps=8, amp=False, compile_mode="default")
    images = torch.randint(0, 256, (2, 3, 16, 24), dtype=torch.uint8, device=device)
    labels = torch.randint(0, 11, (2, 16, 24), device=device)
    model.camera.on_epoch(Schedule(2, 1), int(False))  # epoch 1 of 2 is joint
    for index in range(2):
        step(model, images, labels, index, joint=False)
    before = [p.detach().clone() for p in camera]
    model.camera.on_epoch(Schedule(2, 1), int(True))  # epoch 1 of 2 is joint
    for index in range(2, 4):
        step(model, images, labels, index, joint=True)
    assert all(not torch.equal(a, p.detach()) for a, p in zip(before, camera))


def test_micro_batches_sum_to_the_whole_batch_gradient():
    import copy

    # cross-entropy over all pixels and batch norm on its running statistics (eval mode): a loss that is a mean over
    # images, for which the chunked step must give the whole batch's gradient and loss
    config, model, _, images, labels = _step_and_batch(["loss.ohem_fraction=1.0", "loss.lovasz_weight=0.0",
                                                        "loss.smooth_weight=0.0", "loss.ohem_weight=1.0"])
    images = torch.cat([images, images.flip(-1)])
    labels = torch.cat([labels, labels.flip(-1)])  # a batch of 4
    model.eval()
    chunked_model = copy.deepcopy(model)
    results = []
    for net, micro in ((model, 0), (chunked_model, 3)):  # chunks of 3 + 1: unequal shares
        optimizer = torch.optim.SGD(net.parameters(), lr=0.0)
        step = TrainingStep(config.loss, optimizer, net.camera.learnable_parameters(), 4, False, micro_batch=micro)
        step(net, images, labels, 0, joint=True)
        results.append((step.epoch_statistics(DistributedContext())["train_loss"],
                        [p.grad.clone() for p in net.parameters() if p.grad is not None]))
    (loss, grads), (chunked_loss, chunked_grads) = results
    assert chunked_loss == pytest.approx(loss, rel=1e-5)
    assert len(grads) == len(chunked_grads) > 0
    for a, b in zip(grads, chunked_grads):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-6)


def test_micro_batch_with_a_cuda_graph_is_a_config_error():
    from warpsense.config import ConfigError

    with pytest.raises(ConfigError, match="train.micro_batch"):
        load_config(None, ["train.micro_batch=2", "train.cuda_graph=true"])


def test_step_distils_with_the_configured_mode():
    """The step's distillation part is `loss.distill_mode`'s term between the network's logits and the teacher's on
    the same images, at `loss.distill_temperature`."""
    from warpsense.train.losses import DISTILLATION

    config, model, optimizer, images, labels = _step_and_batch(
        ["loss.distill_weight=0.5", "loss.distill_temperature=3", "loss.distill_mode=pixel"])
    torch.manual_seed(1)
    teacher = build_system(load_config(None, ["noise.enabled=false", "model.width=4"]), 11).eval()
    step = TrainingStep(config.loss, optimizer, model.camera.learnable_parameters(), 4, False, teacher=teacher)
    with torch.no_grad():
        _, parts = step._forward_loss(model, images, labels)
        logits, _ = model(images, False)
        teacher_logits, _ = teacher(images, False)
    expected = DISTILLATION["pixel"](logits, teacher_logits, 3.0)
    torch.testing.assert_close(parts["distill"], expected)
    assert not torch.allclose(parts["distill"], DISTILLATION["pixel"](logits, teacher_logits, 1.0))  # T = 3 used
