"""The timing helpers: the latency timer's eager and replayed paths, and unstable timings flagged."""

from warpsense.bench import timing


def test_latency_is_timed_eager_or_replayed_with_the_repeats_asked(monkeypatch):
    """`time_latency`, the one latency timer of the benchmarks and `warpsense eval --latency`: eager calls through
    `time_function` (50 by default), a CUDA graph's replays through `time_cuda_graph` (100 by default)."""
    calls = []
    monkeypatch.setattr(timing, "time_cuda_graph", lambda function, repeats: calls.append(("graph", repeats)))
    assert timing.time_latency(lambda: None, "cpu")["repeats"] == timing.LATENCY_REPEATS == 50
    assert timing.time_latency(lambda: None, "cpu", repeats=4)["repeats"] == 4
    timing.time_latency(lambda: None, "cuda", graph=True)
    timing.time_latency(lambda: None, "cuda", graph=True, repeats=7)
    assert calls == [("graph", timing.GRAPH_LATENCY_REPEATS), ("graph", 7)] and timing.GRAPH_LATENCY_REPEATS == 100


def test_timings_whose_spread_exceeds_their_median_are_flagged_not_printed_as_results(capsys):
    """Rows measured on a busy machine were printed as results: a timing whose IQR exceeds its median is flagged in
    the record and on its line."""
    from warpsense.bench.runner import Bench
    from warpsense.bench.timing import UNSTABLE_NOTE, _summary

    steady, busy = _summary([1.0, 1.1, 0.9, 1.0, 1.05]), _summary([1.0, 9.0, 0.8, 12.0, 1.1, 10.0])
    assert steady["unstable"] is False and busy["unstable"] is True
    assert busy["iqr_ms"] > busy["median_ms"]
    bench = Bench("cpu", repeats=5)
    bench.record("cfa_mosaic", "warp", "float32", (1, 3, 8, 8), "fwd", steady)
    bench.record("cfa_mosaic", "warp", "float32", (1, 3, 8, 8), "bwd", busy)
    lines = capsys.readouterr().out.strip().splitlines()
    assert UNSTABLE_NOTE not in lines[1] and lines[2].endswith(UNSTABLE_NOTE)
    assert [row["unstable"] for row in bench.records] == [False, True]
