"""`warpsense bench --suite train --quick` on the CPU: every case is timed and recorded (the GPU-only modes,
compiled and CUDA-graph steps, are left out there)."""

from warpsense.bench.train_suite import run_train_suite


def test_quick_cpu_suite_records_every_case():
    records = run_train_suite("cpu", quick=True, metadata={"device_name": "cpu"})
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
