"""The timing helpers: the interleaved eager timer's order of calls and its per-function medians, on a fake clock."""

from warpsense.bench import timing


def test_feature_time_interleaved_calls_in_turn_and_times_each_alone(monkeypatch):
    """Each round calls every function once in the given order after the warm-up rounds; each function's samples
    are the clock's advance during its own calls only (a fake clock: "fast" takes 1 ms, "slow" 3 ms, plus a drift
    of 0.5 ms a round that both share)."""
    clock = {"now": 0.0, "round": 0}
    calls = []

    def advance(name, ms):
        def function():
            calls.append(name)
            clock["now"] += (ms + 0.5 * clock["round"]) / 1e3
            if name == "slow":
                clock["round"] += 1
        return function

    monkeypatch.setattr(timing.time, "perf_counter", lambda: clock["now"])
    result = timing.time_interleaved({"fast": advance("fast", 1.0), "slow": advance("slow", 3.0)}, "cpu",
                                     repeats=5, warmup=2)
    assert calls == ["fast", "slow"] * 7
    # timed rounds 2..6: fast 1 + 0.5 r ms, slow 3 + 0.5 r ms; medians at r = 4
    assert abs(result["fast"]["median_ms"] - 3.0) < 1e-9 and abs(result["slow"]["median_ms"] - 5.0) < 1e-9
    assert result["fast"]["repeats"] == result["slow"]["repeats"] == 5
    assert abs(result["fast"]["iqr_ms"] - result["slow"]["iqr_ms"]) < 1e-9 and result["fast"]["iqr_ms"] > 0


def test_feature_time_interleaved_pairs_each_round_with_the_reference(monkeypatch):
    """Per-round differences to the reference: "slow" is 2 ms slower in every round whatever the drift, so its
    paired median and interval are exactly 2 ms, while its unpaired medians differ by the same 2 ms only because
    the drift is shared."""
    clock = {"now": 0.0, "round": 0}

    def advance(ms, last=False):
        def function():
            clock["now"] += (ms + 0.5 * clock["round"] ** 2) / 1e3
            if last:
                clock["round"] += 1
        return function

    monkeypatch.setattr(timing.time, "perf_counter", lambda: clock["now"])
    result = timing.time_interleaved({"base": advance(1.0), "slow": advance(3.0, last=True)}, "cpu", repeats=9,
                                     warmup=1, reference="base")
    assert "vs_reference_ms" not in result["base"]
    assert abs(result["slow"]["vs_reference_ms"] - 2.0) < 1e-9
    assert all(abs(bound - 2.0) < 1e-9 for bound in result["slow"]["vs_reference_ci95_ms"])


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


def test_feature_median_interval_order_statistics():
    """n = 100: k = floor((100 - 1.96 * 10) / 2) = 40, so the 41st smallest and 41st largest of 0..99 (Conover's
    interval covers the median with ~95% probability); tiny samples get their whole range."""
    assert timing.median_interval([float(v) for v in reversed(range(100))]) == (40.0, 59.0)
    assert timing.median_interval([3.0, 1.0, 2.0]) == (1.0, 3.0)
    assert timing.median_interval([5.0]) == (5.0, 5.0)


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
