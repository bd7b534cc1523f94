"""`warpsense bench`: kernel microbenchmarks and the training suite against the plain-torch baseline."""

from __future__ import annotations

from warpsense.files import check_output_file


def run_bench_command(device: str, suite: str, quick: bool, json_out: str | None, plot_out: str | None,
                      camvid_root: str | None = None, seeds: tuple[int, ...] = (0,)) -> int:
    """Run the suite (`warpsense.bench.runner.run_bench`) after checking its inputs and where its outputs go."""
    from warpsense.bench.runner import run_bench

    check_output_file(json_out, "--json")
    check_output_file(plot_out, "--plot")
    if camvid_root is not None:  # the dataset's own checks, before minutes of other suites
        from warpsense.data.datasets import CamVid

        CamVid(camvid_root, "val", limit=1)
    run_bench(device=device, quick=quick, json_out=json_out, plot_out=plot_out, suite=suite, camvid_root=camvid_root,
              seeds=seeds)
    return 0
