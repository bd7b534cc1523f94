"""`warpsense study`: camera comparisons over cameras x light levels x seeds, each cell an ordinary training run
judged at its final epoch, with intervals over seeds, paired differences to a reference camera and an image-level
bootstrap."""

from warpsense.study.plan import Cell, Plan, PlanError, load_plan
from warpsense.study.report import render_text, study_record
from warpsense.study.runner import run_cells

__all__ = ["Cell", "Plan", "PlanError", "load_plan", "render_text", "run_cells", "study_record"]
