"""tools/scale_tta.py: each set's score is the model's own multi-scale prediction (`warpsense eval --scale-tta`), and
its refusals."""

import pytest
import torch


@pytest.fixture
def tool(load_tool):
    return load_tool("scale_tta")


def test_one_scale_is_plain_evaluation_on_camvid(tool, shared_data):
    """Each set scores as the model's own prediction with those scales (`SensingModel.probabilities`, noise keyed by
    the frame's index in the split; [1] is plain evaluation), by the confusion matrix evaluation uses."""
    from warpsense.data import build_dataset
    from warpsense.system import load_system
    from warpsense.train.metrics import ConfusionMatrix

    records = tool.scale_sets_miou("checkpoints/camvid_codesign.safetensors", str(shared_data / "camvid"), "val",
                                   [[1.0], [0.75, 1.0]], limit=2)
    assert [r["images"] for r in records] == [2, 2]
    model, config, _ = load_system("checkpoints/camvid_codesign.safetensors", "cpu")
    config.data.root = str(shared_data / "camvid")
    dataset = build_dataset(config.data, "val", train=False, seed=config.run.seed)
    model.eval()
    for record in records:
        matrix = ConfusionMatrix(model.network.head.out_channels, "cpu")
        for index in list(range(len(dataset)))[:: len(dataset) // 2][:2]:
            image, label = dataset[index][:2]
            probabilities = model.probabilities(image[None], image_index=torch.tensor([index]),
                                                scales=tuple(record["scales"]))
            matrix.update(probabilities.argmax(dim=1), label[None])
        assert record["miou"] == pytest.approx(matrix.compute()["miou"], abs=1e-12)
    assert records[1]["miou"] != records[0]["miou"]


@pytest.mark.parametrize("sets", ["1;0,1", "a"])
def test_bad_sets_are_one_line_errors(tool, sets, capsys):
    with pytest.raises(SystemExit) as exit_info:
        tool.main(["--sets", sets])
    assert exit_info.value.code == 2
    assert f"--sets {sets!r}:" in capsys.readouterr().err
