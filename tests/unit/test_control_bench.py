"""The control benchmark's figures come from the real prediction and law (a short run, no timing asserted)."""

from __future__ import annotations

import math

from companion.lab.control_bench import format_result, run


def test_the_control_bench_times_both_variants_and_says_so() -> None:
    r = run(blocks=2, per_block=20)
    for name in ("as_captured", "acting_moment"):
        for k in ("predict_us", "tick_us"):
            p = r[name][k]
            assert math.isfinite(p["p50"])
            assert 0.0 < p["p50"] <= p["p95"]
        assert r[name]["tick_us"]["p50"] >= r[name]["predict_us"]["p50"]
    text = format_result(r)
    assert "acting_moment" in text
    assert "% of the 50 ms tick" in text
