"""``hapticloud bench loop --bus``: the result's shape (the figures themselves are benchmarks)."""

from __future__ import annotations

import sys

import pytest
from hapticloud.hardware.control.bench import _machine_stalls, machine_counters, run_bench


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_machine_counters_read_the_kernel() -> None:
    counters = machine_counters()
    assert {"thp_fault_alloc", "thp_collapse_alloc", "steal_ticks"} <= set(counters)
    assert all(isinstance(v, int) and v >= 0 for v in counters.values())


def test_bus_bench_reports_ticks_misses_and_the_machine_counters() -> None:
    res = run_bench("impacts", 1.0)
    enabled = ["ready", "enabled", "bench"]
    if enabled not in [list(tr) for tr in res["transitions"]] and any(
        tr[1] == "fault" for tr in res["transitions"]
    ):
        # A fault before the enable (seen once in a full suite: a drive's feedback lost 11 ms, a
        # stall of the shared 2-core machine). Once more: a bench that never enables fails again.
        print("run again after:", res["transitions"])
        res = run_bench("impacts", 1.0)
    assert res["ticks"] > 600  # 800 Hz for 1 s, less start-up
    # Reached ENABLED (a stall of the shared machine may fault it afterwards, correctly).
    assert enabled in [list(tr) for tr in res["transitions"]], res["transitions"]
    for key in ("tick_us_p99", "misses_per_10k", "body_us", "breakdown_us"):
        assert key in res
    # The enabled ticks apart; the answers read ahead of the deadline; the deferred work counted.
    assert res["tick_us_enabled"]["median"] is not None
    assert "ahead" in res["breakdown_us"] and res["frames_read_ahead_median"] >= 6.0
    assert set(res["deferred"]) == {"snapshot", "refit"}
    assert set(res["machine_stalls"]) == {"count", "max_ms", "faults", "faults_in_stall"}
    if sys.platform.startswith("linux"):
        assert "thp_collapse_alloc" in res["machine_counters_during_run"]


def test_a_fault_in_a_stall_of_the_drives_process_is_told_as_the_machines() -> None:
    # The emulator logs a stall when it wakes; a fault within it (or just after) is the stall's.
    res = {
        "emulator_events": [
            (9.0, -1, "stall", "0.004000 s"),  # before the window
            (10.0, -1, "stall", "0.009257 s"),
            (10.0, 0, "fault", "0x8250"),
            (12.0, -1, "stall", "0.005500 s"),
        ],
        "transitions": [
            (5.0, "ready", "enabled", "bench"),
            (10.001, "enabled", "fault", "watchdog feedback: drive feedback lost (10.55 ms)"),
            (11.0, "enabled", "fault", "watchdog drive_fault: a drive reports a fault"),
        ],
    }
    assert _machine_stalls(res, t_mark=9.5) == {
        "count": 2,
        "max_ms": 9.26,
        "faults": 2,
        "faults_in_stall": 1,
    }
