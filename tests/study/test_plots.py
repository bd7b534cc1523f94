"""The study's figures as written (warpsense/study/report.py's plot_study, warpsense/study/maps.py's plot_maps):
every label inside the figure, intervals within a score's range, a map cell's score clear of the learned paths."""

import matplotlib
import pytest

from tests.study.test_maps import SWEEP, _fabricate, _plan
from warpsense.study import load_plan
from warpsense.study.maps import plot_maps
from warpsense.study.report import plot_study, study_record

matplotlib.use("Agg")


@pytest.fixture
def saved(monkeypatch) -> list:
    """The figures the plot functions save, each with the renderer that drew it (as savefig draws them), instead of
    writing them."""
    import matplotlib.figure

    figures = []

    def save(figure, *args, **kwargs):
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        canvas = FigureCanvasAgg(figure)  # what savefig writes with (plt.close takes the figure's canvas after)
        canvas.draw()
        figures.append((figure, canvas.get_renderer()))

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", save)
    return figures


def _inside(figure, renderer) -> bool:
    """Whether everything drawn lies within the figure (what savefig writes without bbox_inches='tight')."""
    drawn = figure.get_tightbbox(renderer)
    page = figure.bbox_inches
    return drawn.x0 >= page.x0 and drawn.y0 >= page.y0 and drawn.x1 <= page.x1 and drawn.y1 <= page.y1


def test_the_report_figure_keeps_its_colour_bar_label_and_score_intervals_inside(tmp_path, saved):
    """Before: the colour bar's label ('IoU difference to the reference (points x100)') was longer than a row of one
    comparison is tall and was cut at the figure's edges (drawn from -0.03 to 3.14 in on a 2.9 in figure), and a
    score's interval over two seeds reached below 0 mIoU."""
    record = {"study": "s", "reference": "a", "level": 0.95, "plan": {"cameras": [{}, {}]}, "cells": [],
              "splits": {"heldout": {
                  "groups": [{"camera": "a", "light": "night", "miou": {"mean": 0.088, "low": -0.138, "high": 0.314,
                                                                        "n": 4, "folds": 2},
                              "per_class_iou": {"sky": None, "road": None}},
                             {"camera": "b", "light": "night", "miou": {"mean": 0.95, "low": 0.7, "high": 1.2, "n": 2},
                              "per_class_iou": {"sky": None, "road": None}}],
                  "comparisons": [{"camera": "b", "light": "night", "verdict": "not distinguishable",
                                   "per_class_delta": {"sky": -0.013, "road": 0.113}}]}}}
    plot_study(record, tmp_path / "report.png")
    [(figure, renderer)] = saved
    assert _inside(figure, renderer)
    score_axis = figure.axes[0]
    ends = [x for collection in score_axis.collections for segment in collection.get_segments()
            for x, _ in segment]
    assert min(ends) == pytest.approx(0.0) and max(ends) == pytest.approx(1.0)  # [-0.138, 0.314], [0.7, 1.2] clipped


def test_a_map_cells_score_is_written_clear_of_the_learned_paths_start_and_within_0_1(tmp_path, saved):
    """Before: each cell's score was written on its grid point, where a learned path starts (o) and often ends
    (*): the markers covered it; and a two-seed interval was printed below 0 ([-0.144, 0.288])."""
    learned = '\n[[camera]]\nname = "learned"\nset = ["optics.f_number=4.0", "optics.exposure_ms=3.0", ' \
              '"optics.f_number_learnable=true"]\n'
    plan = load_plan(_plan(tmp_path, SWEEP + learned))
    keys = [("", 0), ("", 1)]
    base = {"map_f1p4_t3": 0.40, "map_f1p4_t30": 0.50, "map_f4_t3": 0.05, "map_f4_t30": 0.45, "learned": 0.20}
    scores = {camera: {("", 0): value, ("", 1): value + (0.3 if camera == "map_f4_t3" else 0.02)}
              for camera, value in base.items()}
    _fabricate(tmp_path / "study", plan, scores, {key: [4.0, 4.0, 4.0] for key in keys})  # a path that stays put
    record = study_record(tmp_path / "study", resamples=20, block=2)
    assert plot_maps(record, tmp_path / "map.png")
    [(figure, renderer)] = saved
    assert _inside(figure, renderer)
    [axis, _colour_bar] = figure.axes
    scores_written = [text for text in axis.texts if text.get_text().count("\n") == 1]
    assert len(scores_written) == 4
    lines = axis.get_lines()
    starts = {(line.get_xdata()[0], line.get_ydata()[0]) for line in lines if line.get_marker() == "o"}
    assert starts == {(1.0, 0.0)}  # the learned path starts on grid point (f/4, 3 ms): column 1, row 0
    for text in scores_written:
        box = text.get_window_extent(renderer).transformed(axis.transData.inverted())
        i, j = round(text.get_position()[0]), round(text.get_position()[1])
        assert not box.contains(i, j), text.get_text()  # clear of its grid point, where paths start and end
        assert -0.5 < box.y0 and box.y1 < j + 0.5 and i - 0.5 < box.x0 and box.x1 < i + 0.5  # inside its cell
        assert text.get_zorder() > max(line.get_zorder() for line in lines)  # and over any path that crosses it
        low, high = (float(x) for x in text.get_text().split("\n")[1].strip("[]").split(", "))
        assert 0.0 <= low <= high <= 1.0
