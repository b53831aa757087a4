"""``hapticloud bench loop --bus``: the result's shape (the figures themselves are benchmarks)."""

from __future__ import annotations

import sys

import pytest
from hapticloud.hardware.control.bench import machine_counters, run_bench


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_machine_counters_read_the_kernel() -> None:
    counters = machine_counters()
    assert {"thp_fault_alloc", "thp_collapse_alloc", "steal_ticks"} <= set(counters)
    assert all(isinstance(v, int) and v >= 0 for v in counters.values())


def test_bus_bench_reports_ticks_misses_and_the_machine_counters() -> None:
    res = run_bench("impacts", 1.0)
    assert res["ticks"] > 600  # 800 Hz for 1 s, less start-up
    # Reached ENABLED (a stall of the shared machine may fault it afterwards, correctly).
    assert ["ready", "enabled", "bench"] in [list(tr) for tr in res["transitions"]]
    for key in ("tick_us_p99", "misses_per_10k", "body_us", "breakdown_us"):
        assert key in res
    # The enabled ticks apart; the answers read ahead of the deadline; the deferred work counted.
    assert res["tick_us_enabled"]["median"] is not None
    assert "ahead" in res["breakdown_us"] and res["frames_read_ahead_median"] >= 6.0
    assert set(res["deferred"]) == {"snapshot", "refit"}
    if sys.platform.startswith("linux"):
        assert "thp_collapse_alloc" in res["machine_counters_during_run"]
