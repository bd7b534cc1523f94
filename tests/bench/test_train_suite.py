"""`warpsense bench --suite train --quick` on the CPU: every case is timed and recorded (the GPU-only modes,
compiled and CUDA-graph steps, are left out there)."""

import json

import torch

from warpsense.cli import main


def test_quick_cpu_suite_records_every_case(tmp_path):
    """Through the command, with a --set that changes the network timed (recorded in the JSON's metadata)."""
    out = tmp_path / "train.json"
    assert main(["bench", "--suite", "train", "--quick", "--set", "model.squeeze=true", "--json", str(out)]) == 0
    saved = json.loads(out.read_text())
    assert saved["metadata"]["overrides"] == ["model.squeeze=true"]
    records = saved["records"]
    training = {(r["method"], r["camera"], r["loss"]) for r in records if "images_per_s" in r}
    assert training == {(method, camera, loss) for method, camera in
                        [("torch_baseline", "simple"), ("warpsense", "simple"), ("warpsense", "codesign")]
                        for loss in ("ce", "full")}
    assert all(r["images_per_s"] > 0 and not r["cuda_graph"] and r["compile"] == "off"
               for r in records if "images_per_s" in r)
    timed = [r for r in records if "median_ms" in r]
    cases = [("torch_baseline", "simple"), ("warpsense", "simple"), ("warpsense", "codesign")]
    assert {(r["method"], r["camera"], r["mode"]) for r in timed} == {
        (method, camera, mode) for method, camera in cases for mode in ("eager", "camera fwd+bwd eager")} | {
        ("warpsense", camera, "eager_cached") for camera in ("simple", "codesign")}
    assert all(r["median_ms"] > 0 for r in timed)
    assert {tuple(r["shape"]) for r in timed if r["mode"].startswith("camera")} == {(2, 3, 64, 96)}
    assert all(r["suite"] == "train" and r["device"] == "cpu" for r in records)


def test_train_suite_times_the_presets_network():
    """The suite's network is the one the camvid recipe trains (its preset's [model]), not a fixed stand-in: the same
    parameter count as `warpsense train --config camvid_codesign` builds, in the layout asked for."""
    from warpsense.bench.train_suite import recipe_network
    from warpsense.config import load_config
    from warpsense.models import count_parameters, network_from_config

    expected = network_from_config(load_config("camvid_codesign", []).model, 1, 11, 2)
    for channels_last in (True, False):
        network = recipe_network(channels_last)
        assert count_parameters(network) == count_parameters(expected) == 336_267
        assert network.memory_format == (torch.channels_last if channels_last else torch.contiguous_format)
    # --set changes the network timed: the preset's with squeeze-excitation put back
    assert count_parameters(recipe_network(True, ("model.squeeze=true",))) == 452_591
