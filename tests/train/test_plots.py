"""Run plots: the warm-up / joint boundary on the curves, frames spread over the dataset with a class legend,
and sweeps on one mIoU axis with the operating point marked."""

import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch

from warpsense.train import plots


@pytest.fixture
def figures(monkeypatch):
    """The figures the plot functions close, kept for inspection."""
    kept, close = [], plt.close
    monkeypatch.setattr(plots.plt, "close", kept.append)
    yield kept
    for figure in kept:
        close(figure)


def test_spread_indices_cover_the_dataset():
    assert plots.spread_indices(101, 4) == [0, 33, 67, 100]
    assert plots.spread_indices(3, 4) == [0, 1, 2]
    assert plots.spread_indices(1, 4) == [0]


def test_curves_mark_the_start_of_joint_training(tmp_path, figures):
    records = [{"epoch": e, "train_loss": 1.0 / (e + 1), "phase": "warmup" if e < 3 else "joint",
                **({"val_miou": 0.1 * e} if e % 2 else {})} for e in range(6)]
    plots.plot_curves(records, tmp_path / "curves.png")
    for axis in figures[0].axes:
        vertical = [line for line in axis.get_lines() if line.get_label() == "warm-up | joint"]
        assert len(vertical) == 1 and vertical[0].get_xdata()[0] == 3.5  # between epochs 3 and 4 (1-based)
    assert (tmp_path / "curves.png").stat().st_size > 0


def test_sweep_panels_share_the_miou_axis_and_star_the_operating_point(tmp_path, figures):
    rows = [{"factor": "blur_sigma_px", "value": v, "miou": 0.45 - 0.01 * v, "operating_point": v == 0.0}
            for v in (0.0, 0.5, 1.0)]
    rows += [{"factor": "bits", "value": b, "miou": 0.13 + 0.03 * b, "operating_point": b == 10} for b in (4, 8, 10)]
    plots.plot_sweep(rows, tmp_path / "sweep.png", "robustness sweep: ckpt.safetensors, camvid val, 101 images")
    assert figures[0]._suptitle.get_text() == "robustness sweep: ckpt.safetensors, camvid val, 101 images"
    first, second = figures[0].axes
    assert first.get_ylim() == second.get_ylim()
    starred = [axis.collections[0].get_offsets().tolist() for axis in (first, second)]
    assert starred == [[[0.0, 0.45]], [[10.0, pytest.approx(0.43)]]]


class _Model(torch.nn.Module):
    class _Network(torch.nn.Module):
        head = torch.nn.Conv2d(1, 3, 1)

    network = _Network()

    def forward(self, images):
        logits = torch.zeros(1, 3, *images.shape[-2:])
        logits[:, 1] = 1
        return logits, images.float().mean(dim=1, keepdim=True)


def test_predictions_show_spread_frames_and_a_class_legend(tmp_path, figures):
    class Frames(torch.utils.data.Dataset):
        classes = ("sky", "road", "car")

        def __len__(self):
            return 40

        def __getitem__(self, index):
            return torch.rand(3, 8, 12), torch.from_numpy(np.full((8, 12), index % 3))

    plots.plot_predictions(_Model(), Frames(), "cpu", tmp_path / "predictions.png")
    figure = figures[0]
    titles = [axis.get_title() for axis in figure.axes if axis.get_title().startswith("input")]
    assert titles == [f"input (sRGB), frame {i}" for i in (0, 13, 26, 39)]
    assert [text.get_text() for text in figure.legends[0].get_texts()] == ["sky", "road", "car"]
    assert figure.legends[0]._ncols == 3  # one row: the legend does not wrap


def test_psf_display_window_holds_every_pixel_above_one_percent():
    from warpsense.optics.psf_support import display_half_width

    offsets = np.arange(31) - 15
    radius2 = offsets[:, None] ** 2 + offsets[None, :] ** 2
    narrow, wide = np.exp(-radius2 / (2 * 1.5**2)), np.exp(-radius2 / (2 * 3.0**2))
    # 1% of the peak lies at 3.03 sigma: offsets up to 4 (sigma 1.5) and 9 (sigma 3), plus one pixel of margin
    assert display_half_width(narrow[None, None]) == 5
    assert display_half_width(np.stack([narrow, wide])[None]) == 10  # the widest PSF of the grid decides
    assert display_half_width(np.ones((1, 1, 31, 31))) == 15  # never beyond the kernel


def test_camera_figure_has_a_panel_per_pictured_stage_and_says_whether_it_wrote(tmp_path):
    from types import SimpleNamespace

    from PIL import Image

    from warpsense.camera import Camera
    from warpsense.config import load_config

    both = SimpleNamespace(camera=Camera.from_config(load_config(None, ["optics.enabled=true"])))
    assert plots.plot_camera(both, tmp_path / "both.png")
    cfa_only = SimpleNamespace(camera=Camera.from_config(load_config(None, [])))
    assert plots.plot_camera(cfa_only, tmp_path / "cfa.png")
    assert Image.open(tmp_path / "both.png").width > 1.5 * Image.open(tmp_path / "cfa.png").width  # two panels
    bare = SimpleNamespace(camera=Camera.from_config(load_config(None, ["cfa.enabled=false"])))
    assert not plots.plot_camera(bare, tmp_path / "bare.png") and not (tmp_path / "bare.png").exists()


def test_design_plot_draws_what_was_learned_and_nothing_else(tmp_path, figures):
    records = [{"epoch": e, "f_number": 2.0 + 0.1 * e, "exposure_ms": 10.0, "analog_gain": 4.0 * (1 + 0.05 * e),
                "cfa_layout": "RGGB" if e < 2 else "RCCB"} for e in range(4)]
    assert plots.plot_design(records, tmp_path / "design.png")
    axes = figures[0].axes
    assert [axis.get_ylabel() for axis in axes[:2]] == ["f-number", "analog gain"]  # exposure time did not move
    np.testing.assert_allclose(axes[0].get_lines()[0].get_ydata(), [2.0, 2.1, 2.2, 2.3])
    strip = axes[2].get_images()[0].get_array()  # [sites, epochs, 3]: site 1 turns from green to clear
    assert strip.shape == (4, 4, 3) and strip[1, 0].tolist() == [0, 1, 0] and strip[1, 3].tolist() == [1, 1, 1]
    assert axes[2].get_title() == "CFA: RGGB -> RCCB"
    fixed = [{"epoch": e, "cfa_layout": "RGGB", "exposure_gain": 1.0} for e in range(3)]
    assert not plots.plot_design(fixed, tmp_path / "nothing.png") and not (tmp_path / "nothing.png").exists()


def test_predictions_plot_takes_an_evaluation_set_kept_on_the_device(tmp_path):
    """The run keeps its evaluation set on the GPU (DecodedDataset): the plot moves each frame to the host before
    drawing it (a CUDA tensor has no .numpy(); stood in for here by a tensor type whose .numpy() refuses)."""
    from warpsense.config import load_config
    from warpsense.data import StreetScenes
    from warpsense.system import build_system
    from warpsense.train.plots import plot_predictions

    class OnDevice(torch.Tensor):
        def numpy(self, *args, **kwargs):
            raise TypeError("can't convert a device tensor to numpy: use .cpu() first")

        def cpu(self, *args, **kwargs):
            return self.as_subclass(torch.Tensor)

    class DeviceScenes(StreetScenes):
        def __getitem__(self, index):
            image, label = super().__getitem__(index)
            return image.as_subclass(OnDevice), label.as_subclass(OnDevice)

    dataset = DeviceScenes(2, 32, 48, seed=1)
    model = build_system(load_config(None, ["model.width=4"]), len(dataset.classes))
    plot_predictions(model, dataset, "cpu", tmp_path / "predictions.png", count=2)
    assert (tmp_path / "predictions.png").stat().st_size > 0


def _visible_ticks(axis) -> list[float]:
    low, high = axis.get_xlim()
    return [tick for tick in axis.get_xticks() if low <= tick <= high]


@pytest.mark.parametrize("epochs", [1, 2, 3])
def test_short_runs_plot_every_point_on_whole_epoch_ticks(tmp_path, figures, epochs):
    """A one-epoch curves.png had an empty loss panel (one point of a line without markers) and ticks at 0.96 to
    1.04; design.png had ticks at 1.5 epochs."""
    records = [{"epoch": e, "train_loss": 1.0 - 0.1 * e, "val_miou": 0.2 + 0.1 * e, "phase": "joint",
                "exposure_gain": 1.0 + 0.01 * e, "cfa_layout": "RGGB" if e else "RRRR"} for e in range(epochs)]
    plots.plot_curves(records, tmp_path / "curves.png")
    for axis in figures[0].axes:
        assert axis.get_lines()[0].get_marker() not in (None, "None", "", " ")
        ticks = _visible_ticks(axis)
        assert ticks == [float(e) for e in range(1, epochs + 1)], ticks
    if epochs > 1:
        assert plots.plot_design(records, tmp_path / "design.png")
        for axis in figures[1].axes:
            assert _visible_ticks(axis) == [float(e) for e in range(1, epochs + 1)]


def test_design_marks_a_uniform_cfa_start_undecided_not_as_its_argmax(tmp_path, figures):
    """A CFA started uniform exported "RRRR" (the argmax of a tie, the first candidate) and design.png titled
    "CFA: RRRR -> CCRB": the recorded choice marks tied sites "?", drawn grey."""
    from warpsense.camera.cfa import CFA, FILTERS, UNDECIDED_COLOUR

    cfa = CFA("RCCB", 2, "softmax", init_logit=0.0, candidates="RGBC")
    start = cfa.summary()
    assert start["cfa_layout"] == "RRRR" and start["cfa_choice"] == "????"  # the export is unchanged
    with torch.no_grad():
        cfa.logits.copy_(torch.tensor([[[0.3, 0.8, 0.0, 1.0], [0.2, 0.9, 0.0, 1.0]],
                                       [[1.0, 0.5, 0.0, 0.2], [0.0, 0.0, 1.0, 0.5]]]))
    end = cfa.summary()
    assert end["cfa_layout"] == end["cfa_choice"] == "CCRB"
    records = [{"epoch": 0, **start}, {"epoch": 1, **end}]
    assert plots.plot_design(records, tmp_path / "design.png")
    strip = figures[0].axes[-1]
    assert strip.get_title() == "CFA: ???? -> CCRB"
    colours = strip.get_images()[0].get_array()  # [sites, epochs, 3]
    np.testing.assert_allclose(colours[:, 0], [UNDECIDED_COLOUR] * 4)
    np.testing.assert_allclose(colours[:, 1], [FILTERS[letter] for letter in "CCRB"])
    # records written before the choice was recorded still plot, from the export
    old = [{k: v for k, v in record.items() if k != "cfa_choice"} for record in records]
    assert plots.plot_design(old, tmp_path / "design_old.png")
    assert figures[1].axes[-1].get_title() == "CFA: RRRR -> CCRB"


def test_camera_picture_shows_each_sites_exported_filter_beside_its_mix(figures):
    """camera.png drew the four sites near-yellow (the softmax mix in use) under the letters C, C, R, B: each site
    now has a strip in its exported filter's colour, its letter with that filter's weight, in a readable colour."""
    from warpsense.camera.cfa import CFA, FILTERS

    cfa = CFA("RCCB", 2, "softmax", init_logit=0.0, candidates="RGBC")
    with torch.no_grad():
        cfa.logits.copy_(torch.tensor([[[0.3, 0.8, 0.0, 1.0], [0.2, 0.9, 0.0, 1.0]],
                                       [[1.0, 0.5, 0.0, 0.2], [0.0, 0.0, 1.0, 0.5]]]))
    figure, axis = plt.subplots()
    figures.append(figure)
    cfa.draw(axis)
    strips = [tuple(patch.get_facecolor()[:3]) for patch in axis.patches]
    assert strips == [FILTERS[letter] for letter in "CCRB"]
    weights = torch.softmax(cfa.logits.detach(), dim=-1).amax(dim=-1).flatten()
    texts = [(text.get_text(), text.get_color()) for text in axis.texts]
    assert [text for text, _ in texts] == [f"{letter} {float(w):.0%}" for letter, w in zip("CCRB", weights)]
    assert [colour for _, colour in texts] == ["black", "black", "white", "white"]  # on clear, red, blue
