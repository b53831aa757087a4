"""The control process: deadline pacing, the loop in its own process, torque gating, watchdogs.

Reactions are asserted from the recorded per-tick log the process returns, not from sleeping.
"""

from __future__ import annotations

import gc
import math
import os
import time

import numpy as np
import pytest
from hapticloud.hardware.control import STATE_CODES, ControlProcess, DeadlineLoop, try_sched_fifo

ENABLED = STATE_CODES["enabled"]
FAULT = STATE_CODES["fault"]


# ----- deadline loop -----------------------------------------------------------------------------
def test_deadline_loop_counts_injected_overrun():
    dl = DeadlineLoop(0.002, spin_s=0.0005)
    gc_before = gc.isenabled()
    dl.start()
    try:
        assert not gc.isenabled()
        starts = []
        for _ in range(30):
            k, t_k = dl.wait()
            starts.append((k, t_k, time.perf_counter()))
            if k == 10:
                time.sleep(0.005)  # overruns its period and the next deadline
            dl.done()
    finally:
        dl.stop()
    assert gc.isenabled() == gc_before
    st = dl.stats()
    assert st.misses >= 1
    assert st.overruns >= 1
    assert st.ticks == 30
    # Deadlines are absolute: t_k = t0 + k * period, and no tick started before its deadline.
    for k, t_k, started in starts:
        assert t_k == pytest.approx(dl.t0 + k * 0.002)
        assert started >= t_k
    # The ticks after the overrun that fell more than a period behind were skipped, not bunched.
    assert max(k for k, _, _ in starts) >= 29


def test_deadline_loop_quiet_run_has_no_misses_and_fifo_falls_back_cleanly():
    dl = DeadlineLoop(0.004, spin_s=0.001, fifo_priority=10)
    dl.start()
    try:
        for _ in range(10):
            dl.wait()
            dl.done()
    finally:
        dl.stop()
    st = dl.stats()
    assert st.ticks == 10
    assert isinstance(st.sched_fifo, bool) and st.sched_note
    assert st.as_dict()["misses_per_10k"] >= 0.0
    # Scheduling policy restored after stop.
    if hasattr(os, "sched_getscheduler"):
        assert os.sched_getscheduler(0) != os.SCHED_FIFO


def test_deadline_loop_runs_work_ahead_in_the_spin_window_only():
    dl = DeadlineLoop(0.002, spin_s=0.0008)
    calls: list[tuple[int, float]] = []
    ticks = []
    dl.start()
    try:
        for _ in range(20):
            k, t_k = dl.wait(lambda: calls.append((dl.tick, time.perf_counter())))
            ticks.append((k, t_k))
            if k == 5:
                time.sleep(0.0035)  # past the next deadline: no work ahead for tick 6
            dl.done()
    finally:
        dl.stop()
    # Called before its deadline (the previous tick index is still current), never after it.
    by_tick = {k + 1: t for k, t in calls}
    assert len(by_tick) == len(calls)
    for k, t_k in ticks:
        if k in by_tick:
            assert t_k - 0.0008 - 0.0005 < by_tick[k] < t_k
    assert 6 not in by_tick
    assert 7 in by_tick  # woke inside tick 7's spin window: the work ahead fits
    assert len(calls) >= 15


def test_try_sched_fifo_never_raises():
    ok, note = try_sched_fifo(1)
    assert isinstance(ok, bool) and note
    if ok:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


# ----- the process -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def run():
    """One process run: ~0.3 s ready, enable, ~0.3 s enabled, drive 2 faults, stop. The loop and
    the drives' process ask for SCHED_FIFO, as in a session, so that other load does not stall
    them (the normal scheduler when refused)."""
    cp = ControlProcess("impacts", fifo_priority=60)
    info = cp.start(timeout=60.0)
    pid = cp.pid
    try:
        time.sleep(0.3)
        cp.enable("test")
        time.sleep(0.3)
        cp.inject_drive_fault(2)
        time.sleep(0.15)
        snaps = cp.snapshots()
        assert cp.alive
    finally:
        result = cp.stop(timeout=20.0)
    return {"cp": cp, "info": info, "pid": pid, "snaps": snaps, "result": result}


def test_process_runs_returns_snapshots_and_stops_cleanly(run):
    cp, res, snaps = run["cp"], run["result"], run["snaps"]
    assert run["info"]["pid"] == run["pid"] != os.getpid()
    assert isinstance(run["info"]["sched_fifo"], bool)
    assert res is not None and cp.error is None
    assert res["ticks"] > 400  # ~0.75 s at 800 Hz
    assert len(snaps) > 20
    seqs = [s.seq for s in snaps]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert all(len(s.q) == 6 and len(s.tau_sent) == 6 for s in snaps)
    assert {s.state for s in snaps} >= {"ready", "enabled"}
    # Stopped and reaped: no live child, no zombie.
    assert not cp.alive
    stat = f"/proc/{run['pid']}/stat"
    if os.path.exists(stat):
        with open(stat) as f:
            assert f.read().split(")")[-1].split()[0] != "Z"
    # The bus ran: every SYNC answered by six feedback frames once running.
    counters = res["link_counters"]
    assert counters["syncs_sent"] >= res["ticks"]
    assert counters["send_errors"] == 0


def test_drive_answers_are_decoded_before_the_deadline(run):
    log = run["result"]["log"]
    on = log["state"] == ENABLED
    # The six answers to the last SYNC arrive within the period: read in the spin, not the tick.
    assert np.median(log["ahead_frames"][on]) >= 6
    assert np.median(log["ahead_us"][on]) > 0.0


def test_no_torque_before_enable_and_torque_after(run):
    log = run["result"]["log"]
    state, tau = log["state"], log["tau_sent"]
    assert (state == ENABLED).any()
    first_enabled = int(np.argmax(state == ENABLED))
    assert first_enabled > 0
    assert np.all(tau[:first_enabled] == 0.0)
    assert np.all(tau[state != ENABLED] == 0.0)
    # Once the drives follow the enable, torque (gravity compensation) flows.
    assert np.abs(tau[state == ENABLED]).sum() > 0.0


def test_drive_fault_turns_torque_off_within_four_ticks(run):
    res = run["result"]
    log = res["log"]
    fault_cmd = [c for c in res["commands"] if c[2:] == ("inject", "inject_drive_fault")]
    assert len(fault_cmd) == 1
    injected = fault_cmd[0][0]  # tick at which the emulator's injector was told
    tau = log["tau_sent"]
    earlier = [tr for tr in res["transitions"] if tr[2] == "fault" and tr[0] < log["t"][injected]]
    if earlier:
        # A fault before the injection (a stall of this shared machine: feedback lost, or a
        # drive's own command timeout; seen once in a full local suite under load) turned the
        # torque off first. Nothing is left to test of the injected one: skip, with the evidence.
        pytest.skip(f"the session faulted before the injection (machine overloaded): {earlier}")
    assert np.abs(tau[injected - 1]).sum() > 0.0  # torque flowed right before
    off = np.flatnonzero(np.all(tau[injected:] == 0.0, axis=1))
    assert off.size and off[0] <= 4
    # It stays off (latched), the session went to FAULT, for the right reason.
    assert np.all(tau[injected + off[0] :] == 0.0)
    assert log["state"][-1] == FAULT
    assert any(tr[2] == "fault" and "drive_fault" in tr[3] for tr in res["transitions"])
    seen = np.flatnonzero(log["any_fault"][injected:] > 0)
    assert seen.size and seen[0] <= off[0]


def test_controller_change_applies_when_not_enabled_and_is_refused_when_enabled():
    from hapticloud.core.control import ControllerConfig

    # The simulation clock: a stall of this (shared) machine slows the simulated drives with
    # the loop instead of faulting the session, which this test is not about.
    cp = ControlProcess("impacts", fifo_priority=None, emulator="stepped", sim_clock=True)
    cp.start(timeout=60.0)
    try:
        time.sleep(0.2)
        cfg = ControllerConfig().replace_path("min_acceleration.damping_1_per_s", 5.0)
        cp.configure(controller=cfg)  # READY: applied
        time.sleep(0.1)
        cp.enable("test")
        time.sleep(0.1)
        # ENABLED: refused, twelve times in one tick (more events than a snapshot carries).
        for _ in range(12):
            cp.configure(controller=ControllerConfig())
        time.sleep(0.1)
        with pytest.raises(TypeError):
            cp.configure(controller="not a config")
    finally:
        res = cp.stop(timeout=20.0)
    # Nothing read the snapshots during the run (the pipe filled and snapshots were dropped);
    # every event still arrives, in order, by the end (stop() drains the pipe).
    events = [e for s in cp.snapshots() for e in s.events if e[1] == "config"]
    assert [e[2] for e in events] == [
        "controller applied",
        *["controller change refused: disable the session first"] * 12,
    ]
    assert [e[0] for e in events] == sorted(e[0] for e in events)
    assert res is not None and (res["log"]["state"] == ENABLED).any()
    assert not any(tr[2] == "fault" for tr in res["transitions"]), res["transitions"]


@pytest.mark.parametrize(("sim_clock", "faults"), [(True, False), (False, True)])
def test_a_stalled_machine_slows_the_simulation_instead_of_faulting(sim_clock, faults):
    """The process is stopped for 150 ms (a machine that cannot keep up, injected): with the
    simulated drives on the loop's clock the session stays enabled and says the simulation fell
    behind; on wall time the same stall is lost drive feedback and the session faults."""
    import signal

    cp = ControlProcess("impacts", fifo_priority=None, emulator="stepped", sim_clock=sim_clock)
    cp.start(timeout=60.0)
    try:
        time.sleep(0.3)
        cp.enable("test")
        time.sleep(0.3)
        os.kill(cp.pid, signal.SIGSTOP)
        time.sleep(0.15)
        os.kill(cp.pid, signal.SIGCONT)
        time.sleep(1.2)
    finally:
        res = cp.stop(timeout=20.0)
    faulted = any(tr[2] == "fault" for tr in res["transitions"])
    assert faulted is faults, res["transitions"]
    factors = [s.sim_time_factor for s in cp.snapshots()]
    if sim_clock:
        assert (res["log"]["state"][-20:] == ENABLED).all()
        assert 0.0 < min(f for f in factors if math.isfinite(f)) < 0.95
    else:
        assert all(math.isnan(f) for f in factors)


def test_a_loop_refused_sched_fifo_takes_the_fallback_nice(monkeypatch):
    """Refused SCHED_FIFO, the loop still runs ahead of the app's perception worker (nice -5)
    and window (nice 5): nice FALLBACK_NICE, set as is; refused that too, it says only the first."""
    from hapticloud.hardware.control import deadline

    def refuse(*_args):
        raise PermissionError("not permitted")

    asked = []
    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(os, "setpriority", lambda which, who, value: asked.append(value))
    ok, note = try_sched_fifo(80)
    assert not ok and asked == [deadline.FALLBACK_NICE] and deadline.FALLBACK_NICE < -5
    assert note.endswith(f"normal scheduler at nice {deadline.FALLBACK_NICE}")
    monkeypatch.setattr(os, "setpriority", refuse)
    ok, note = try_sched_fifo(80)
    assert not ok and note.endswith("; normal scheduler")
