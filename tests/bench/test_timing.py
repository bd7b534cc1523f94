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
