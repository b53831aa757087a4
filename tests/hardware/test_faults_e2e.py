"""End-to-end fault injection through :class:`ControlProcess`: every reaction and its timing.

Each module-scoped fixture is one run of the control process (the 800 Hz loop in its own
process, the six emulated drives, the session and the watchdogs) that follows a script of
commands, camera traffic and injected faults; the tests then read the reactions and their timing
from the per-tick log the process returns (``res["log"]``, ``transitions``, ``reactions``,
``commands``, ``link_events``). Sleeps only let time pass; nothing is concluded from them.

Conventions used below: ``i`` is an index into the per-tick log; a command (enable, reset, a
fault injection) is handled at the start of tick ``res["commands"][...][0]``; with
``emulator="stepped"`` the drives act on an injection in that same tick and the master sees the
result in the feedback it polls one tick later. Times are ``time.monotonic`` seconds, shared by
the parent and the child, so frame times sent from here compare with the log's ``t`` directly.

The runs (about 3 s of wall time each, most of it start-up):

``cam``      stepped, two cameras at 30 Hz: one camera stops, later the estimates stop.
``drive``    stepped, a swaying arm: a drive faults mid-motion, the fault is cleared, a reset.
``loss1``    stepped: 1 % frame loss in both directions.
``loss10``   stepped: 10 % loss of the drives' frames (feedback, heartbeats, EMCY).
``hb``       stepped: one drive's heartbeat stops (watchdog and link heartbeat timeouts equal).
``hb_cfg``   stepped: the same with a longer ``WatchdogConfig.heartbeat_timeout_s``.
``bus``      stepped: the bus goes off.
``sigint``   emulator in its own process: enable and SIGINT back to back, then a reset.
"""

from __future__ import annotations

import math
import os
import re
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from hapticloud.core.perception import SurfaceEstimate
from hapticloud.hardware.control import STATE_CODES, ControlProcess
from hapticloud.hardware.drives import DriveBusConfig
from hapticloud.hardware.session import ReactionLevel, WatchdogConfig

PERIOD_S = 1.0 / 800.0
#: The issue's bound for a torque-off reaction: 5 ms = 4 ticks at 800 Hz.
TORQUE_OFF_TICKS = 4
TORQUE_OFF_S = 0.005

READY = STATE_CODES["ready"]
ENABLED = STATE_CODES["enabled"]
FAULT = STATE_CODES["fault"]
ESTOP = STATE_CODES["emergency_stop"]
NONE = int(ReactionLevel.NONE)
HOLD = int(ReactionLevel.HOLD_SURFACE)
DAMPING = int(ReactionLevel.DAMPING)
TORQUE_OFF = int(ReactionLevel.TORQUE_OFF)

#: The link's timeouts in the control process (its DriveBusConfig is built with the defaults).
BUS = DriveBusConfig()

#: Watchdog timeouts of the ``cam`` run: short, but well above the 33 ms between frames.
MAIN_WATCHDOGS = {"camera_timeout_s": 0.1, "estimate_timeout_s": 0.1, "hold_timeout_s": 0.15}
MAIN_WD = WatchdogConfig.from_dict(MAIN_WATCHDOGS)
DEFAULT_WD = WatchdogConfig()


# ----- a patient who sways the arm (picklable: it crosses into the spawned processes) ----------
class SwayingArm:
    """``model -> ArmDynamics``: the default rigid arm with a sinusoidal joint torque added (a
    patient moving the arm), so that a fault can be injected mid-motion."""

    def __init__(self, amplitude_nm: float = 2.0, freq_hz: float = 1.5) -> None:
        self.amplitude_nm = amplitude_nm
        self.freq_hz = freq_hz

    def __call__(self, model: Any) -> _Sway:
        from hapticloud.hardware.drives.emulator import RigidArm

        return _Sway(RigidArm(model), self.amplitude_nm, self.freq_hz)


class _Sway:
    def __init__(self, arm: Any, amplitude_nm: float, freq_hz: float) -> None:
        self._arm = arm
        self._a = amplitude_nm
        self._w = 2.0 * math.pi * freq_hz
        self._t = 0.0
        self._shape = np.array([1.0, -1.0, 1.0, 0.5, 0.0, 0.0])

    def __call__(self, q: Any, qd: Any, tau: Any, dt: float) -> Any:
        self._t += dt
        push = self._a * math.sin(self._w * self._t) * self._shape
        return self._arm(q, qd, tau + push, dt)


# ----- camera traffic ---------------------------------------------------------------------------
def _head_surface() -> tuple[np.ndarray, np.ndarray]:
    """Point and outward normal of the impacts scene's head facing the start HIP (the 5 deg tilt
    of the ellipsoid is ignored: a few mm, irrelevant here)."""
    centre = np.array([-0.01, 0.18, 1.29])
    axes = np.array([0.095, 0.075, 0.11])
    hip0 = np.array([0.293, 0.005, 1.29])
    u = (hip0 - centre) / np.linalg.norm(hip0 - centre)
    point = centre + u / math.sqrt(float(np.sum((u / axes) ** 2)))
    normal = (point - centre) / axes**2
    return point, normal / np.linalg.norm(normal)


HEAD_POINT, HEAD_NORMAL = _head_surface()


class CameraFeeder:
    """Sends, at ``rate_hz``, for each camera either an estimate of the head surface, a bare
    frame time, or nothing (``mode``: ``"estimate"``, ``"frame"``, ``"off"``), and records every
    ``(t, camera, kind)`` it sent (``t`` is the frame time the loop receives)."""

    def __init__(self, cp: ControlProcess, rate_hz: float = 30.0) -> None:
        self._cp = cp
        self._period = 1.0 / rate_hz
        self.mode = {"front": "estimate", "right45": "estimate"}
        self.sent: list[tuple[float, str, str]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="camera-feeder", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)

    def set(self, **modes: str) -> float:
        """Change modes; returns the time of the change."""
        with self._lock:
            self.mode.update(modes)
            return time.monotonic()

    def _run(self) -> None:
        nxt = time.monotonic()
        while not self._stop.is_set():
            with self._lock:
                for name, mode in self.mode.items():
                    t = time.monotonic()
                    if mode == "estimate":
                        est = SurfaceEstimate(
                            t, name, HEAD_POINT, HEAD_NORMAL, True, quality=1.0, method="oracle"
                        )
                        self._cp.send_estimate(est)
                    elif mode == "frame":
                        self._cp.camera_frame(name, t)
                    else:
                        continue
                    self.sent.append((t, name, mode))
            nxt += self._period
            self._stop.wait(max(0.0, nxt - time.monotonic()))

    def last(self, camera: str | None, kind: str, before: float) -> float:
        """Time of the last ``kind`` sent for ``camera`` (any for ``None``) before ``before``."""
        times = [
            t
            for t, c, k in self.sent
            if k == kind and (camera is None or c == camera) and t < before
        ]
        return max(times)

    def first(self, camera: str, kind: str, after: float) -> float:
        return min(t for t, c, k in self.sent if k == kind and c == camera and t >= after)


# ----- running a script -------------------------------------------------------------------------
@dataclass
class Run:
    name: str
    res: dict[str, Any]
    info: dict[str, Any]
    marks: dict[str, float] = field(default_factory=dict)
    feeder: CameraFeeder | None = None
    snaps: list[Any] = field(default_factory=list)

    @property
    def log(self) -> dict[str, np.ndarray]:
        return self.res["log"]

    def commands(self, name: str, detail: str | None = None) -> list[int]:
        """Log indices of the ticks that handled the commands ``name`` (``detail``), in order."""
        return [
            int(c[0])
            for c in self.res["commands"]
            if c[2] == name and (detail is None or c[3] == detail)
        ]

    def tick_at(self, t: float) -> int:
        """Index of the first tick at or after time ``t``."""
        return int(np.searchsorted(self.log["t"], t))


def _run(
    name: str,
    script: Callable[[ControlProcess, dict[str, float], CameraFeeder | None], None],
    *,
    emulator: str = "stepped",
    watchdogs: dict[str, Any] | None = None,
    dynamics: Any = None,
    cameras: bool = False,
) -> Run:
    cp = ControlProcess(
        "impacts",
        emulator=emulator,
        # As in a session: SCHED_FIFO when permitted (root here and in CI), so that the other
        # tests' load does not stall the loop; the normal scheduler otherwise (then stalls are
        # detected in the log and the affected tests skip with the measured figure).
        fifo_priority=60,
        watchdogs=watchdogs,
        dynamics=dynamics,
        log_ticks=1 << 13,
    )
    info = cp.start(timeout=60.0)
    marks: dict[str, float] = {}
    feeder = CameraFeeder(cp) if cameras else None
    # Read the snapshots as they come (the loop drops those that do not fit in the pipe).
    snaps: list[Any] = []
    done = threading.Event()

    def pump() -> None:
        while not done.wait(0.01):
            snaps.extend(cp.snapshots())

    reader = threading.Thread(target=pump, name="snapshot-reader", daemon=True)
    reader.start()
    try:
        if feeder is not None:
            feeder.start()
        script(cp, marks, feeder)
        assert cp.alive, cp.error
    finally:
        if feeder is not None:
            feeder.stop()
        done.set()
        reader.join(2.0)
        res = cp.stop(timeout=20.0)
    assert res is not None, f"run {name}: no result ({cp.error})"
    assert cp.error is None, cp.error
    return Run(name, res, info, marks, feeder, snaps + cp.snapshots())


def _enable(cp: ControlProcess, settle_s: float = 0.25) -> None:
    time.sleep(0.2)
    cp.enable("test")
    time.sleep(settle_s)


def _first(mask: np.ndarray, start: int = 0) -> int | None:
    idx = np.flatnonzero(mask[start:])
    return start + int(idx[0]) if idx.size else None


def _all_zero(tau: np.ndarray) -> np.ndarray:
    return np.all(tau == 0.0, axis=1)


def _reactions_between(run: Run, i0: int, i1: int) -> list[tuple[Any, ...]]:
    t = run.log["t"]
    t1 = t[i1] if i1 < len(t) else math.inf
    return [r for r in run.res["reactions"] if t[i0] <= r[1] < t1]


def _late_ms(reason: str) -> float:
    m = re.search(r"\(([-\d.]+) ms\)", reason)
    assert m, reason
    return float(m.group(1))


def _only_feedback_damping(reactions: list[tuple[Any, ...]]) -> None:
    """Every reaction change is DAMPING for late feedback (older than ``feedback_late_s``, not
    older than ``feedback_lost_s``) or back to NONE."""
    late, lost = DEFAULT_WD.feedback_late_s * 1e3, DEFAULT_WD.feedback_lost_s * 1e3
    for _, _, level, source, reason in reactions:
        assert level in ("NONE", "DAMPING"), reactions
        if level == "DAMPING":
            assert source == "feedback", reactions
            assert late <= _late_ms(reason) <= lost, reason


def _flowing(run: Run, i0: int, i1: int) -> float:
    """Share of the ticks ``i0 .. i1 - 1`` that sent some torque. The link blocks the torque of
    a drive whose feedback is older than ``feedback_timeout_s`` (3.75 ms), which a late tick on a
    loaded machine produces now and then; a torque-off reaction zeroes every tick."""
    return float(np.mean(np.abs(run.log["tau_sent"][i0:i1]).sum(axis=1) > 0.0))


def _skip_if_stalled(run: Run, i0: int, i1: int, *, late_share: float = 0.1) -> None:
    """Without SCHED_FIFO (refused), or on a VM that stalls even SCHED_FIFO processes, a tick can
    come so late, or be preempted so long, that the feedback is older than ``feedback_lost_s`` when
    it is read, and the feedback watchdog then rightly turns torque off; or so many ticks come
    late that the feedback watchdog damps a good share of them. Neither says anything about the
    fault under test: skip, with the evidence from the log."""
    log = run.log
    j0 = max(i0, 1)
    t, work = log["t"], log["body_us"] * 1e-6
    stall = (t[j0:i1] - t[j0 - 1 : i1 - 1]) + work[j0:i1]  # previous tick start -> this one's end
    if stall.size and stall.max() > DEFAULT_WD.feedback_lost_s:
        pytest.skip(
            f"run {run.name}: the loop stalled {stall.max() * 1e3:.1f} ms (machine overloaded)"
        )
    # The drives' process stalled (it says so, when the stall ends): their answers came late,
    # through no fault of the link or the loop. Its clock is the loop's (time.monotonic).
    if i1 > j0:
        for ev_t, _, kind, detail in run.res["emulator_events"]:
            if kind != "stall":
                continue
            began = ev_t - float(detail.split()[0])
            if began <= t[i1 - 1] and ev_t >= t[j0]:
                pytest.skip(f"run {run.name}: the drives' process stalled {detail} (machine)")
    gaps = t[j0:i1] - t[j0 - 1 : i1 - 1]
    late = np.mean(gaps > DEFAULT_WD.feedback_late_s) if gaps.size else 0.0
    if late > late_share:
        pytest.skip(f"run {run.name}: {late:.0%} of the ticks late by > 3 ms (machine overloaded)")


def _skip_if_starved(run: Run, camera: str, kind: str, t0: float, t1: float) -> None:
    """Skip when the camera thread here was starved: no ``kind`` of ``camera`` for nearly the
    camera and estimate timeouts (0.1 s), so that a watchdog not under test may have fired."""
    assert run.feeder is not None
    times = sorted(t for t, c, k in run.feeder.sent if c == camera and k == kind and t0 <= t < t1)
    gaps = np.diff(times)
    assert len(times) >= 2, (camera, kind, t0, t1)
    if gaps.max() > 0.095:
        pytest.skip(
            f"run {run.name}: the camera thread was starved, no {kind} of {camera} for "
            f"{gaps.max() * 1e3:.0f} ms (machine overloaded)"
        )


def _quiet_or_feedback(run: Run, i0: int, i1: int) -> None:
    """Ticks ``i0 .. i1 - 1`` are NONE (no approach cap) or a DAMPING for late feedback (a late
    tick on a loaded machine; capped like every reaction)."""
    reaction, limit = run.log["reaction"][i0:i1], run.log["approach_limit_mps"][i0:i1]
    assert np.all((reaction == NONE) | (reaction == DAMPING)), reaction
    assert np.all(np.isnan(limit) == (reaction == NONE))
    _only_feedback_damping(_reactions_between(run, i0, i1))


# ----- the runs ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cam_run() -> Run:
    def script(cp: ControlProcess, marks: dict[str, float], feeder: CameraFeeder | None) -> None:
        assert feeder is not None
        _enable(cp, 0.3)
        marks["cam_off"] = feeder.set(right45="off")
        time.sleep(0.4)  # hold after 0.1 s without a frame, damping 0.15 s later
        marks["cam_on"] = feeder.set(right45="estimate")
        time.sleep(0.2)
        marks["est_off"] = feeder.set(front="frame", right45="frame")
        time.sleep(0.2)  # estimate stale after 0.1 s
        marks["est_on"] = feeder.set(front="estimate", right45="estimate")
        time.sleep(0.1)

    return _run("cam", script, watchdogs=MAIN_WATCHDOGS, cameras=True)


@pytest.fixture(scope="module")
def drive_run() -> Run:
    def script(cp: ControlProcess, marks: dict[str, float], feeder: Any) -> None:
        _enable(cp, 0.3)
        cp.inject_drive_fault(2, persistent=True)
        time.sleep(0.1)
        cp.clear_drive_fault(2)
        time.sleep(0.05)
        cp.reset()
        time.sleep(0.15)
        cp.enable("after reset")
        time.sleep(0.1)

    return _run("drive", script, dynamics=SwayingArm())


@pytest.fixture(scope="module")
def loss1_run() -> Run:
    def script(cp: ControlProcess, marks: dict[str, float], feeder: Any) -> None:
        _enable(cp)
        cp.inject_fault("set_loss", rx=0.01, tx=0.01)
        time.sleep(0.5)
        cp.inject_fault("set_loss", rx=0.0, tx=0.0)
        time.sleep(0.05)

    return _run("loss1", script)


@pytest.fixture(scope="module")
def loss10_run() -> Run:
    def script(cp: ControlProcess, marks: dict[str, float], feeder: Any) -> None:
        _enable(cp)
        cp.inject_fault("set_loss", tx=0.1)
        time.sleep(1.0)
        cp.inject_fault("set_loss", tx=0.0)
        time.sleep(0.05)
        cp.emergency_stop("test: API emergency stop")
        time.sleep(0.05)

    return _run("loss10", script)


def _heartbeat_script(wait_s: float) -> Callable[..., None]:
    def script(cp: ControlProcess, marks: dict[str, float], feeder: Any) -> None:
        _enable(cp)
        cp.inject_fault("set_heartbeat_loss", 4, True)
        time.sleep(wait_s)

    return script


@pytest.fixture(scope="module")
def hb_run() -> Run:
    # The watchdog's heartbeat timeout set equal to the link's, so the expiry is the same
    # whichever of the two decides.
    wd = {"heartbeat_timeout_s": BUS.heartbeat_timeout_s}
    return _run("hb", _heartbeat_script(0.1), watchdogs=wd)


@pytest.fixture(scope="module")
def hb_cfg_run() -> Run:
    return _run("hb_cfg", _heartbeat_script(0.2), watchdogs={"heartbeat_timeout_s": 0.08})


@pytest.fixture(scope="module")
def bus_run() -> Run:
    def script(cp: ControlProcess, marks: dict[str, float], feeder: Any) -> None:
        _enable(cp)
        cp.inject_fault("set_bus_off", True)
        time.sleep(0.08)

    return _run("bus", script)


@pytest.fixture(scope="module")
def sigint_run() -> Run:
    def script(cp: ControlProcess, marks: dict[str, float], feeder: Any) -> None:
        time.sleep(0.3)
        assert cp.pid is not None
        cp.enable("test")
        os.kill(cp.pid, signal.SIGINT)
        time.sleep(0.25)
        cp.reset()
        time.sleep(0.1)

    return _run("sigint", script, emulator="process")


RUNS = (
    "cam_run",
    "drive_run",
    "loss1_run",
    "loss10_run",
    "hb_run",
    "hb_cfg_run",
    "bus_run",
    "sigint_run",
)


# ----- every run --------------------------------------------------------------------------------
@pytest.mark.parametrize("run_name", RUNS)
def test_torque_within_drive_limits_and_none_before_enable(run_name: str, request) -> None:
    run: Run = request.getfixturevalue(run_name)
    tau = run.log["tau_sent"]
    limits = np.array(run.info["torque_limits_nm"])
    assert limits.shape == (6,) and np.all(limits > 0.0)
    assert np.all(np.isfinite(tau))
    assert np.all(np.abs(tau) <= limits + 1e-9), np.abs(tau).max(axis=0)
    enables = run.commands("enable")
    assert enables, "every run enables"
    assert np.all(tau[: enables[0]] == 0.0)
    # Torque only ever in ENABLED (and not under TORQUE_OFF).
    state, reaction = run.log["state"], run.log["reaction"]
    assert np.all(tau[state != ENABLED] == 0.0)
    assert np.all(tau[reaction == TORQUE_OFF] == 0.0)
    assert run.res["deadline"]["ticks"] == run.res["ticks"]


# ----- frame loss -------------------------------------------------------------------------------
def test_frame_loss_1pct_stays_enabled_without_torque_off(loss1_run: Run) -> None:
    run = loss1_run
    log = run.log
    on, off = run.commands("inject", "set_loss")
    end = off + 8  # until the last frame that could have been lost is overdue
    assert off - on > 300  # ~0.5 s
    _skip_if_stalled(run, run.commands("enable")[0], end)
    reactions = _reactions_between(run, on, end)
    assert np.all(log["state"][on:end] == ENABLED), reactions
    assert np.all(log["reaction"][on:end] < TORQUE_OFF), reactions
    # At most the feedback watchdog stirs: two lost answers of one drive in a row (P ~ 6e-4
    # per tick at 1 %) or a late tick leave the feedback older than feedback_late_s.
    _only_feedback_damping(reactions)
    # Torque kept flowing (gravity compensation is never zero on the shoulder) but in ticks in
    # which a drive's feedback was older than feedback_timeout_s, where the link blocks it.
    assert _flowing(run, on, end) > 0.5
    assert run.res["link_counters"]["feedback_missing"] > 0  # frames really were lost


def test_frame_loss_10pct_damping_only_as_the_feedback_watchdog_implies(loss10_run: Run) -> None:
    """Until anything turns torque off: DAMPING only from the feedback watchdog, each time with
    the feedback older than ``feedback_late_s`` (3 ms: two lost answers of one drive in a row)
    and not older than ``feedback_lost_s`` (10 ms), each episode over as soon as the drive
    answers again, a bounded share of the ticks; NONE otherwise."""
    run = loss10_run
    log = run.log
    on, off = run.commands("inject", "set_loss")
    _skip_if_stalled(run, run.commands("enable")[0], on)
    assert log["state"][on] == ENABLED
    end = _first(log["reaction"] == TORQUE_OFF, on)
    end = off if end is None else min(end, off)
    assert end - on >= 16  # a heartbeat trip needs >= 2 lost heartbeats: >= 20 ms
    _skip_if_stalled(run, on, end)
    reactions = _reactions_between(run, on, end)
    _only_feedback_damping(reactions)
    damping = log["reaction"][on:end] == DAMPING
    assert np.all(log["reaction"][on:end] <= DAMPING)
    assert np.all(log["state"][on:end] == ENABLED)
    assert damping.mean() < 0.5  # ~6 % from the loss (6 drives x 0.1^2), plus late ticks
    edges = np.flatnonzero(np.diff(np.r_[0, damping.astype(int), 0]))
    episodes = edges[1::2] - edges[::2]
    assert episodes.size == 0 or episodes.max() < DEFAULT_WD.feedback_lost_s / PERIOD_S
    assert _flowing(run, on, end) > 0.5


def test_frame_loss_10pct_never_turns_torque_off(loss10_run: Run) -> None:
    run = loss10_run
    log = run.log
    on, off = run.commands("inject", "set_loss")
    _skip_if_stalled(run, run.commands("enable")[0], off + 8)
    reactions = _reactions_between(run, on, off + 8)
    # What a failure needs to be told apart from a stall: the drives' own events, the longest
    # gap between ticks and the longest tick body in the window.
    drives = [e for e in run.res["emulator_events"] if e[2] in ("stall", "command_timeout")]
    gap_ms = float(np.diff(log["t"][on : off + 8]).max()) * 1e3
    body_ms = float(log["body_us"][on : off + 8].max()) * 1e-3
    why = (reactions, drives[:6], f"tick gap {gap_ms:.2f} ms, body {body_ms:.2f} ms")
    assert np.all(log["reaction"][on : off + 8] < TORQUE_OFF), why
    assert np.all(log["state"][on : off + 8] == ENABLED), why


def test_api_emergency_stop_zeroes_torque_in_its_tick(loss10_run: Run) -> None:
    run = loss10_run
    (i,) = run.commands("estop")
    assert np.all(run.log["state"][i:] == ESTOP)
    assert np.all(run.log["tau_sent"][i:] == 0.0)
    tr = [x for x in run.res["transitions"] if x[2] == "emergency_stop"]
    assert tr and tr[-1][0] == run.log["t"][i] and "API" in tr[-1][3]


# ----- drive fault ------------------------------------------------------------------------------
def test_drive_fault_mid_motion_turns_torque_off_within_4_ticks(drive_run: Run) -> None:
    run = drive_run
    log = run.log
    (inj,) = run.commands("inject", "inject_drive_fault")
    (reset,) = run.commands("reset")
    _skip_if_stalled(run, run.commands("enable")[0], reset)
    tau = log["tau_sent"]
    # Mid-motion: torque flowing and the arm moving just before.
    assert log["state"][inj - 1] == ENABLED and np.abs(tau[inj - 1]).sum() > 0.0
    before = [s for s in run.snaps if inj - 80 <= s.tick < inj]
    assert before, "no snapshot in the 0.1 s before the fault"
    assert max(max(abs(v) for v in s.qd) for s in before) > 0.05  # rad/s
    # The fault shows in the feedback of the next SYNC (stepped drives answer in the tick).
    seen = _first(log["any_fault"] > 0, inj)
    assert seen is not None and seen - inj <= 1
    off = _first(_all_zero(tau), seen)
    assert off is not None
    assert off - seen <= TORQUE_OFF_TICKS
    assert log["t"][off] - log["t"][seen] <= TORQUE_OFF_S
    # Off and latched until the reset; the session in FAULT for the drive fault.
    assert np.all(_all_zero(tau[off:reset]))
    assert np.all(log["reaction"][seen:reset] == TORQUE_OFF)
    assert np.all(log["state"][seen:reset] == FAULT)
    (tr,) = [x for x in run.res["transitions"] if x[2] == "fault"]
    assert tr[0] == log["t"][seen] and "drive_fault" in tr[3]
    r = [x for x in run.res["reactions"] if x[2] == "TORQUE_OFF"]
    assert r and r[0][1] == log["t"][seen] and r[0][3] == "drive_fault"


def test_reset_after_the_fault_clears_goes_back_to_ready(drive_run: Run) -> None:
    run = drive_run
    log = run.log
    (clear,) = run.commands("inject", "clear_drive_fault")
    (reset,) = run.commands("reset")
    enable = run.commands("enable")[-1]
    assert clear < reset < enable
    _skip_if_stalled(run, run.commands("enable")[0], enable + 1)
    # The drive's own fault is gone soon after the reset (fault-reset controlwords).
    assert not np.any(log["any_fault"][reset + 20 : enable])
    # One reset, once the cause is gone: READY within 25 ms, then enable is accepted.
    ready = _first(log["state"] == READY, reset)
    assert ready is not None and ready - reset <= 20, log["state"][reset : reset + 40]
    assert log["state"][enable] == ENABLED


# ----- heartbeat --------------------------------------------------------------------------------
def _heartbeat_expiry_bounds(run: Run, timeout_s: float) -> tuple[int, float, float]:
    """(injection tick, earliest, latest expiry): the drive's last heartbeat reached the link at
    most one heartbeat period plus a tick before the injection tick and at the latest in it."""
    (inj,) = run.commands("inject", "set_heartbeat_loss")
    t_inj = float(run.log["t"][inj])
    earliest = t_inj - BUS.heartbeat_period_s - 2 * PERIOD_S + timeout_s
    latest = t_inj + PERIOD_S + timeout_s
    return inj, earliest, latest


def test_heartbeat_loss_turns_torque_off_within_5ms_of_expiry(hb_run: Run) -> None:
    run = hb_run
    log = run.log
    timeout = BUS.heartbeat_timeout_s
    inj, earliest, latest = _heartbeat_expiry_bounds(run, timeout)
    _skip_if_stalled(run, run.commands("enable")[0], len(log["t"]))
    # The link stamps the moment it finds the heartbeat overdue; that is the expiry, to a tick.
    lost = [e for e in run.res["link_events"] if e[1] == 4 and e[2] == "heartbeat_lost"]
    lost = [e for e in lost if e[0] >= log["t"][inj]]
    assert len(lost) == 1, run.res["link_events"]
    found = lost[0][0]
    assert earliest <= found <= latest + PERIOD_S
    i_found = int(np.searchsorted(log["t"], found, side="right")) - 1  # the tick that polled it
    # The tick before still had a live heartbeat: the expiry lies after it.
    expired_after = float(log["t"][i_found - 1])
    assert log["reaction"][i_found - 1] < TORQUE_OFF and log["state"][i_found - 1] == ENABLED
    off = _first(_all_zero(log["tau_sent"]) & (log["reaction"] == TORQUE_OFF), inj)
    assert off is not None
    assert log["t"][off] - expired_after <= TORQUE_OFF_S
    assert off - i_found <= TORQUE_OFF_TICKS - 1
    assert np.all(_all_zero(log["tau_sent"][off:]))
    assert np.all(log["state"][off:] == FAULT)
    (tr,) = [x for x in run.res["transitions"] if x[2] == "fault"]
    assert "heartbeat" in tr[3]
    # Feedback stayed fresh: it was the heartbeat, nothing else.
    assert np.all(log["complete"][inj:off] > 0)


def test_configured_heartbeat_timeout_decides_torque_off(hb_cfg_run: Run) -> None:
    run = hb_cfg_run
    log = run.log
    inj, earliest, latest = _heartbeat_expiry_bounds(run, 0.08)
    _skip_if_stalled(run, run.commands("enable")[0], len(log["t"]))
    off = _first(log["reaction"] == TORQUE_OFF, inj)
    assert off is not None
    why = (run.res["transitions"][-2:], run.res["reactions"][-3:])
    assert earliest < log["t"][off] <= latest + TORQUE_OFF_S, why


# ----- bus off ----------------------------------------------------------------------------------
def test_bus_off_is_feedback_lost_torque_off_within_4_ticks(bus_run: Run) -> None:
    """In the control process the master's bus is not a fault-injecting bus (the injector lives
    with the drives), so the link never reports ``bus_off``: it sees every drive fall silent.
    Its torque gate (feedback older than ``feedback_timeout_s`` = 3.75 ms) zeroes the torque
    within 4 ticks, the feedback watchdog damps at ``feedback_late_s`` and turns torque off with
    the session in FAULT at ``feedback_lost_s``; the drives fault on their command timeout."""
    run = bus_run
    log = run.log
    (inj,) = run.commands("inject", "set_bus_off")
    _skip_if_stalled(run, run.commands("enable")[0], inj + 12)
    tau = log["tau_sent"]
    t = log["t"]
    assert log["state"][inj] == ENABLED and np.abs(tau[inj - 1]).sum() > 0.0
    assert not [e for e in run.res["link_events"] if e[2] == "bus_off"]
    # The last SYNC answered was sent in tick inj - 1.
    zero = _first(_all_zero(tau), inj)
    assert zero is not None and zero - inj <= TORQUE_OFF_TICKS
    assert np.all(_all_zero(tau[zero:]))
    lost_s = DEFAULT_WD.feedback_lost_s
    off = _first(log["reaction"] == TORQUE_OFF, inj)
    assert off is not None
    assert t[off] - t[inj - 1] > lost_s  # not before the feedback was 10 ms old
    assert t[off - 1] - t[inj] <= lost_s  # and in the first tick after that
    assert np.all(log["reaction"][inj:off] <= DAMPING)
    assert np.all(log["state"][off:] == FAULT)
    (tr,) = [x for x in run.res["transitions"] if x[2] == "fault"]
    assert tr[0] == t[off] and "feedback" in tr[3] and "lost" in tr[3]
    r = [x for x in run.res["reactions"] if x[2] == "TORQUE_OFF"]
    assert r[0][3] == "feedback"
    # The drives, without commands, fault on their own 5 ms command timeout.
    timeouts = {e[1] for e in run.res["emulator_events"] if e[2] == "command_timeout"}
    assert timeouts == set(range(6))


# ----- cameras and estimates --------------------------------------------------------------------
def test_camera_stop_holds_surface_within_a_tick_then_damps(cam_run: Run) -> None:
    """One camera stops: HOLD_SURFACE with the approach capped at ``hold_v_min_m_s`` in the
    first tick past ``camera_timeout_s`` after its last frame, DAMPING in the first tick past
    ``hold_timeout_s`` of holding; both lift when the camera is back."""
    run = cam_run
    feeder = run.feeder
    assert feeder is not None
    log = run.log
    t, reaction, limit = log["t"], log["reaction"], log["approach_limit_mps"]
    v_min = MAIN_WD.hold_v_min_m_s
    last = feeder.last("right45", "estimate", run.marks["cam_on"])
    assert last < run.marks["cam_off"] + 0.05
    back = feeder.first("right45", "estimate", run.marks["cam_on"])
    i0, i_back = run.tick_at(last), run.tick_at(back)
    # A stall anywhere since the enable can fault the session before this window opens.
    _skip_if_stalled(run, run.commands("enable")[0], i_back)
    _skip_if_starved(run, "front", "estimate", last - 0.3, back + 0.1)
    _skip_if_starved(run, "right45", "estimate", last - 0.3, last + 1e-9)
    assert np.all(log["state"][i0 - 40 : i_back] == ENABLED)
    _quiet_or_feedback(run, i0 - 40, i0)
    reactions = _reactions_between(run, i0, i_back)
    camera = [r for r in reactions if r[3].startswith("camera:")]
    assert camera and camera[0][2] == "HOLD_SURFACE" and camera[0][3] == "camera:right45"
    # HOLD_SURFACE in the first tick past camera_timeout_s, not before.
    hold = _first((t - last) > MAIN_WD.camera_timeout_s, i0)
    assert hold is not None
    _quiet_or_feedback(run, i0, hold)
    assert reaction[hold] >= HOLD and limit[hold] == v_min
    assert camera[0][1] >= t[hold]
    if reaction[hold] == HOLD:  # (not inside a late-feedback DAMPING that masks the change)
        assert camera[0][1] == t[hold]
    # DAMPING in the first tick at which the hold has lasted longer than hold_timeout_s.
    damp = _first((t - t[hold]) > MAIN_WD.hold_timeout_s, hold)
    assert damp is not None and damp < i_back
    assert np.all(reaction[hold:damp] >= HOLD)
    _only_feedback_damping(
        [r for r in _reactions_between(run, hold, damp) if r[2] != "HOLD_SURFACE"]
    )
    assert reaction[damp] == DAMPING and limit[damp] == v_min
    if reaction[damp - 1] == HOLD:
        assert any(r[1] == t[damp] and r[2:4] == ("DAMPING", "hold") for r in reactions)
    # Until the camera is back: damped, capped, ENABLED, torque flowing (compensation).
    assert np.all(reaction[damp:i_back] == DAMPING) and np.all(limit[hold:i_back] == v_min)
    assert _flowing(run, damp, i_back) > 0.5
    # The camera is back: the watchdog quiet again within a few ticks, the cap lifted.
    quiet = _first(reaction == NONE, i_back)
    assert quiet is not None and quiet - i_back <= 12 and np.isnan(limit[quiet])


def test_stale_estimate_caps_approach_at_v_min_within_a_tick(cam_run: Run) -> None:
    """Frames keep coming but no estimate: HOLD_SURFACE (source ``estimate``) with the approach
    capped at ``hold_v_min_m_s`` in the first tick past ``estimate_timeout_s``."""
    run = cam_run
    feeder = run.feeder
    assert feeder is not None
    log = run.log
    t, reaction, limit = log["t"], log["reaction"], log["approach_limit_mps"]
    v_min = MAIN_WD.hold_v_min_m_s
    last = feeder.last(None, "estimate", run.marks["est_on"])
    assert last < run.marks["est_off"] + 0.05
    # Frames kept coming (camera watchdog quiet); only the estimate went stale.
    for camera in ("front", "right45"):
        assert feeder.last(camera, "frame", run.marks["est_on"]) > last + 0.1
    back = feeder.first("front", "estimate", run.marks["est_on"])
    i0, i_back = run.tick_at(last), run.tick_at(back)
    # A stall anywhere since the enable can fault the session before this window opens.
    _skip_if_stalled(run, run.commands("enable")[0], i_back)
    for camera in ("front", "right45"):
        _skip_if_starved(run, camera, "estimate", last - 0.3, last + 1e-9)
        _skip_if_starved(run, camera, "frame", last, back)
    assert np.all(log["state"][i0 - 40 : i_back] == ENABLED)
    _quiet_or_feedback(run, i0 - 40, i0)
    hold = _first((t - last) > MAIN_WD.estimate_timeout_s, i0)
    assert hold is not None and hold < i_back
    _quiet_or_feedback(run, i0, hold)
    assert reaction[hold] >= HOLD and limit[hold] == v_min
    stale = [r for r in _reactions_between(run, i0, i_back) if r[3] == "estimate"]
    assert stale and stale[0][2] == "HOLD_SURFACE" and stale[0][1] >= t[hold]
    if reaction[hold] == HOLD:
        assert stale[0][1] == t[hold]
    assert np.all(reaction[hold:i_back] >= HOLD) and np.all(limit[hold:i_back] == v_min)
    assert not [r for r in _reactions_between(run, i0, i_back) if r[3].startswith("camera:")]
    quiet = _first(reaction == NONE, i_back)
    assert quiet is not None and quiet - i_back <= 12 and np.isnan(limit[quiet])


# ----- emergency stop ---------------------------------------------------------------------------
def test_sigint_during_enable_is_an_emergency_stop_with_no_torque(sigint_run: Run) -> None:
    run = sigint_run
    log = run.log
    assert run.info["emulator"] == "process"
    (enable,) = run.commands("enable")
    (stop,) = run.commands("estop", "SIGINT")
    assert abs(stop - enable) <= TORQUE_OFF_TICKS  # sent back to back
    tau = log["tau_sent"]
    assert np.all(tau[: min(enable, stop)] == 0.0)
    assert np.all(tau[stop:] == 0.0)
    assert np.all(log["state"][stop:] != ENABLED)
    (reset,) = run.commands("reset")
    assert np.all(log["state"][stop:reset] == ESTOP)
    tr = [x for x in run.res["transitions"] if x[2] == "emergency_stop"]
    assert tr and tr[0][3] == "SIGINT" and tr[0][0] == log["t"][stop]
    # Whichever came first: no tick sent torque between the enable and the e-stop either (the
    # drives need 3 SYNCs to reach OPERATION ENABLED).
    assert np.all(tau[min(enable, stop) :] == 0.0)


def test_reset_after_emergency_stop_goes_back_to_ready(sigint_run: Run) -> None:
    run = sigint_run
    (reset,) = run.commands("reset")
    ready = _first(run.log["state"] == READY, reset)
    assert ready is not None and ready - reset <= 20
