"""tools/scale_tta.py: the CFA-keeping resize, plain evaluation as its one-scale set, and its refusals."""

import pytest
import torch


@pytest.fixture
def tool(load_tool):
    return load_tool("scale_tta")


def test_resize_keeps_every_pixel_on_its_cfa_site(tool):
    """A mosaic whose value names its site (R 1, G 2 and 3, B 4): resized by any scale, every site still holds its
    own value, because each site plane is resized on its own (bilinear of a constant plane is that constant)."""
    sites = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    mosaic = sites.repeat(6, 8)[None, None]  # 12 x 16, RGGB
    for scale in (0.5, 0.75, 1.25, 1.5):
        resized = tool.cfa_resize(mosaic, scale, 2)
        height, width = resized.shape[-2:]
        assert height % 2 == 0 and width % 2 == 0 and height == 2 * round(6 * scale)
        torch.testing.assert_close(resized, sites.repeat(height // 2, width // 2)[None, None])
    assert tool.cfa_resize(mosaic, 1.0, 2) is mosaic
    with pytest.raises(ValueError, match="1x1 and 2x2"):
        tool.cfa_resize(mosaic, 0.5, 4)


def test_one_scale_is_plain_evaluation_on_camvid(tool, shared_data):
    """The set [1] is the model's own prediction (`SensingModel.probabilities`, noise keyed by the frame's index in
    the split), scored by the confusion matrix evaluation uses: equal mIoU."""
    from warpsense.data import build_dataset
    from warpsense.system import load_system
    from warpsense.train.metrics import ConfusionMatrix

    records = tool.scale_sets_miou("checkpoints/camvid_codesign.safetensors", str(shared_data / "camvid"), "val",
                                   [[1.0], [0.75, 1.0]], limit=2)
    assert [r["images"] for r in records] == [2, 2]
    model, config, _ = load_system("checkpoints/camvid_codesign.safetensors", "cpu")
    config.data.root = str(shared_data / "camvid")
    dataset = build_dataset(config.data, "val", train=False, seed=config.run.seed)
    matrix = ConfusionMatrix(model.network.head.out_channels, "cpu")
    model.eval()
    for index in list(range(len(dataset)))[:: len(dataset) // 2][:2]:
        image, label = dataset[index][:2]
        matrix.update(model.probabilities(image[None], image_index=torch.tensor([index])).argmax(dim=1), label[None])
    assert records[0]["miou"] == pytest.approx(matrix.compute()["miou"], abs=1e-12)
    assert records[1]["miou"] != records[0]["miou"] and 0 <= records[1]["miou"] <= 1


@pytest.mark.parametrize("sets", ["1;0,1", "a"])
def test_bad_sets_are_one_line_errors(tool, sets, capsys):
    with pytest.raises(SystemExit) as exit_info:
        tool.main(["--sets", sets])
    assert exit_info.value.code == 2
    assert f"--sets {sets!r}:" in capsys.readouterr().err
