"""An extended run stopped before its new end (issue 60, defect 5): at the first continued epoch the earlier end's
evaluation.json and plots move aside (evaluation.epoch<E>.json, <plot>.epoch<E>.png), so the run holds no evaluation
beside its newer checkpoint and config.json: it reads as unfinished, `warpsense study` resumes it as a partial cell,
and resuming it writes the new end's evaluation."""

import json
import shutil

import pytest

from tests.train.test_continuations import TINY
from warpsense.cli import main
from warpsense.config import load_config
from warpsense.train import engine
from warpsense.train.run_dir import LAST


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    return engine.train(load_config(None, [*TINY, f"run.output_dir={root}", "run.name=tiny"]), progress=False)


def test_an_interrupted_extension_leaves_an_unfinished_run_that_resumes_to_its_new_end(finished_run, tmp_path,
                                                                                       monkeypatch, capsys):
    run = tmp_path / "tiny"
    shutil.copytree(finished_run, run)
    (run / "curves.png").write_bytes(b"the old end's plot")
    old_evaluation = (run / engine.EVALUATION).read_text()
    assert json.loads(old_evaluation)["epoch"] == 0

    def stopped(*args, **kwargs):  # Ctrl-C after the continued epoch, before the new end's evaluation
        raise KeyboardInterrupt

    monkeypatch.setattr(engine, "final_evaluation", stopped)
    assert main(["train", "--resume-dir", str(run), "--extend", "1", "--no-progress"]) == 130
    capsys.readouterr()
    assert json.loads((run / "config.json").read_text())["train"]["epochs"] == 2  # the continuation's config
    assert not (run / engine.EVALUATION).exists()  # nothing says the run is finished
    assert (run / "evaluation.epoch1.json").read_text() == old_evaluation  # the earlier end's, named by its epochs
    assert (run / "curves.epoch1.png").read_bytes() == b"the old end's plot" and not (run / "curves.png").exists()

    from warpsense.study.plan import Cell
    from warpsense.study.study_dir import cell_state

    study = tmp_path / "study"
    cell = Cell(camera="c", light="night", seed=0)
    shutil.copytree(run, study / "runs" / cell.run_name)
    assert cell_state(study, cell) == "partial"  # a study resumes it instead of reporting the old end

    monkeypatch.undo()
    assert main(["train", "--resume-dir", str(run), "--no-progress"]) == 0  # resumes to the new end
    assert json.loads((run / engine.EVALUATION).read_text())["epoch"] == 1
    assert (run / LAST).is_file() and (run / "evaluation.epoch1.json").is_file()


def test_superseded_names():
    assert engine.superseded_name("evaluation.json", 12) == "evaluation.epoch12.json"
    assert engine.superseded_name("curves.png", 3) == "curves.epoch3.png"
