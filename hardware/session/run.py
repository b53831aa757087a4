"""``hapticloud run SCENE --hardware``: a scene's session through the hardware layer, in real time.

What runs where:

- **control process** (:class:`~hapticloud.hardware.control.process.ControlProcess`): the 800 Hz
  loop on absolute deadlines: drive feedback, session state machine, watchdogs, the fusion of the
  camera estimates and the haptic tick built from the scene (as ``hapticloud run`` builds it),
  torque commands over CAN FD;
- **drive emulator process**: six emulated CiA 402 drives moving the exoskeleton, whose dynamics
  are the scene's plant with the scene's patient pushing the handle
  (:class:`~hapticloud.hardware.drives.scene_arm.SceneArmFactory`);
- **perception process** (spawned here, outside the loop): the one perception worker
  (:func:`hapticloud.hardware.perception.session_worker`): each of the scene's cameras, at its
  rate, renders the scene's world with the robot where the control loop says it is (the shared
  :class:`~hapticloud.hardware.control.shared_state.RobotStateBlock`), runs its pipeline for that
  HIP and sends the estimate (capture time on :func:`time.monotonic`) straight down the control
  process's estimates pipe, no earlier than the camera's ``latency_s`` after capture; the loop
  fuses the estimates at 800 Hz. Every estimate goes, an invalid one too ("nothing near the
  HIP" is fresh news for the estimate watchdog; the loop's fusion admits only what it should).
  Frames the renderer could not keep up with are dropped and counted
  (``estimates.skipped_frames``);
- **this process**: enables the session, drains the loop's snapshots and samples the robot's HIP
  from the same block (every ~1 ms) for the ground truth: the true margin of the HIP sphere to
  the scene's bodies and walls
  (:meth:`~hapticloud.core.scene.assembly.Assembly.true_margin`), which never reaches the
  controller.

Scene time 0 is the first tick of the enabled session (the patient's script starts when the
drives first apply torque, a few ticks later). Unlike the deterministic ``hapticloud run`` this is
real time: perception is asynchronous, its latency is what rendering and processing take on this
machine, deadline misses are real, and two runs are not bit-identical.

The control loop has no handle force sensor: the tick runs without ``interaction_torque`` (the
deterministic run feeds it ``J^T F_hand`` when ``robot.force_sensor`` is set).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from functools import partial
from typing import Any

import numpy as np
from hapticloud.core.haptics.unknown import SpaceState, SpaceTransition
from hapticloud.core.studies.stats import json_float, summary
from hapticloud.core.studies.verdict import Verdict, judge, space_summary

__all__ = ["HARDWARE_MODE", "run_session", "summary_lines"]

#: What the report says about how the session ran.
HARDWARE_MODE = "through the hardware layer: control process + emulated drives"

_CONNECTED = 1
_READY = 2
_ENABLED = 3
_FAULT = 4
_STARTUP_RESETS = 3
"""Faults before enable that ``run --hardware`` resets by itself. On a loaded machine a stall
while the perception process starts (importing its libraries) can hold back the drives' feedback
past ``feedback_lost_s``; the watchdog faults the session, rightly, with no torque flowing."""
_STATE_NAMES = {0: "disconnected", 1: "connected", 2: "ready", 3: "enabled", 4: "fault", 5: "estop"}


class _HipSampler:
    """Reads the robot state block; keeps one sample per control tick it sees."""

    def __init__(self, read: Callable[[], Any]) -> None:
        self._read = read
        self.t: list[float] = []
        self.hip: list[np.ndarray] = []
        self.state: list[int] = []
        self._last_tick = -1

    def sample(self) -> Any:
        st = self._read()
        if st is not None and st.tick != self._last_tick:
            self._last_tick = st.tick
            self.t.append(st.t)
            self.hip.append(st.hip_m)
            self.state.append(st.state_code)
        return st


def _spread(values: Any, scale: float = 1.0) -> dict[str, float | int | None]:
    """Median, p99 and max of the finite values (JSON-safe)."""
    return summary(values, scale, percentiles=(99,), count=False)


def _start_perception(scene: str, overrides: Any, cp: Any, n_joints: int, record_sink: Any) -> Any:
    """The scene's cameras in a perception process of their own (the one perception worker,
    :func:`~hapticloud.hardware.perception.session_worker`), built and ready to go."""
    from ..perception import PerceptionProcess, session_worker

    perception = PerceptionProcess(
        session_worker,
        (scene, overrides, cp.state_block_name, n_joints, cp.estimate_connection, record_sink),
    )
    perception.wait_ready()
    return perception


def _stop_perception(perception: Any) -> dict[str, Any]:
    """The perception process stopped; its figures as the report carries them."""
    stats = perception.stop()
    dropped = stats.pop("sink_dropped", {})
    return {"record_dropped": int(dropped.get("RecorderSink", 0)), **stats} if stats else {}


class _StateWaiter:
    """Waits for the session's states from this process, keeping every snapshot it drains (the
    report's) and the session's last state change (what a timeout names)."""

    def __init__(self, cp: Any, snaps: list[Any]) -> None:
        self._cp = cp
        self._snaps = snaps
        self.last_change = ""
        #: Every fault's state change, in order (one per entry into FAULT).
        self.fault_changes: list[str] = []

    def _drain(self) -> None:
        for snap in self._cp.snapshots():
            self._snaps.append(snap)
            for _, kind, text in snap.events:
                if kind == "state":
                    self.last_change = text
                    if text.startswith(f"{_STATE_NAMES[_FAULT]}:"):
                        self.fault_changes.append(text)

    def wait(self, codes: tuple[int, ...], timeout_s: float) -> Any:
        """The loop's state once its code is one of ``codes``; raises after ``timeout_s``."""
        cp = self._cp
        end = time.monotonic() + timeout_s
        seen = None
        while time.monotonic() < end:
            st = cp.robot_state()
            if st is not None:
                seen = st.state_code
                if seen in codes:
                    self._drain()
                    return st
            if not cp.alive:
                break
            time.sleep(0.002)
        self._drain()
        where = "no tick yet" if seen is None else f"last seen {_STATE_NAMES.get(seen, seen)}"
        if self.last_change:
            where += f", {self.last_change}"
        wanted = " or ".join(_STATE_NAMES.get(c, str(c)) for c in codes)
        raise RuntimeError(
            f"control process: session did not reach {wanted} in "
            f"{timeout_s:g} s ({where}){': ' + cp.error if cp.error else ''}"
        )

    def ready(self, timeout_s: float) -> list[str]:
        """Wait for READY. A fault on the way (no torque flows before enable) is reset once its
        cause has cleared, as the operator would press Reset, at most :data:`_STARTUP_RESETS`
        times; returns those faults' state changes, which the report lists."""
        end = time.monotonic() + timeout_s
        n_faults = 0

        def named() -> list[str]:
            # A fault's text comes with a snapshot, up to a few ticks after the state changed.
            known = self.fault_changes[:n_faults]
            return known + ["fault"] * (n_faults - len(known))

        while True:
            st = self.wait((_READY, _FAULT), max(0.0, end - time.monotonic()))
            if st.state_code == _READY:
                return named()
            n_faults += 1
            if n_faults > _STARTUP_RESETS:
                raise RuntimeError(
                    f"control process: session faulted {n_faults} times before enable "
                    f"(last: {named()[-1]})"
                )
            # The loop refuses a reset while a torque-off cause is active: ask again until it
            # takes or the time is out.
            while True:
                self._cp.reset()
                try:
                    self.wait((_READY, _CONNECTED), min(0.2, max(0.0, end - time.monotonic())))
                    break
                except RuntimeError as err:
                    if not self._cp.alive:
                        raise
                    if time.monotonic() >= end:
                        raise RuntimeError(
                            f"control process: session faulted before enable and its fault did "
                            f"not clear in {timeout_s:g} s ({named()[-1]})"
                        ) from err


def run_session(
    scene: str,
    overrides: Mapping[str, Any] | None = None,
    duration_s: float | None = None,
    *,
    emulator: str = "process",
    cameras: bool = True,
    fifo_priority: int | None = 80,
    plant_substeps: int | None = 1,
    progress: Callable[[str], None] | None = None,
    record: str | None = None,
    record_limit_bytes: int | None = None,
) -> dict[str, Any]:
    """Run ``scene`` in real time through the control process and the emulated drives.

    Parameters
    ----------
    scene
        Scene file or shipped scene name.
    overrides
        ``--set`` style overrides.
    duration_s
        Seconds of enabled session (default: the scene's ``duration_s``).
    emulator
        Where the drives run (:data:`~hapticloud.hardware.control.process.EMULATOR_MODES`).
    cameras
        Run the scene's cameras (the perception process); ``False``: no estimates are sent
        (walls only, or the loop holds no surface).
    fifo_priority
        SCHED_FIFO priority the control loop asks for (``None``: do not ask).
    plant_substeps
        Integration steps of the emulated plant per drive cycle (1/800 s); ``None``: the scene's
        ``loop.substeps``, as the deterministic run. One step (as the emulator's
        :class:`~hapticloud.hardware.drives.emulator.RigidArm`) costs the emulator process
        ~130 µs per cycle instead of ~500 µs.
    progress
        Called with a line of text now and then.
    record
        Record the session to this ``.mcap`` file (:mod:`hapticloud.hardware.recording`): the
        perception process sends each frame and estimate, this process the loop's snapshots;
        a recording that fails (disk full) stops with an alarm and the session goes on.
    record_limit_bytes
        A quota for the recording (writes past it fail as a full disk does; tests).

    Returns
    -------
    dict
        The JSON-ready report (see :func:`summary_lines` for the headline figures).

    Raises
    ------
    ConfigError
        Bad scene, overrides or duration (including an infeasible scene).
    RuntimeError
        The control process failed.
    """
    say = progress or (lambda _text: None)
    ovr = dict(overrides) if overrides else None
    loaded, sim, duration = _checked_scene(scene, ovr, duration_s, emulator)
    cams = sim.cameras if cameras else []
    cp = _control_process(scene, ovr, emulator, fifo_priority, plant_substeps, duration)
    recorder = _recorder(record, loaded, record_limit_bytes)
    say(f"starting the control process and the emulated drives ({emulator}) ...")
    wall0 = time.monotonic()
    info = cp.start(timeout=120.0)
    live = _LiveSession(cp, sim.hip_radius_m, recorder, say)
    start_perception = None
    if cams:
        sink = recorder.sink if recorder else None
        start_perception = partial(_start_perception, scene, ovr, cp, sim.robot.n_joints, sink)
    estimates, result, recording = live.run(start_perception, duration, loaded.name)
    if result is None:
        raise RuntimeError(f"control process failed: {cp.error or 'no result'}")
    wall_s = time.monotonic() - wall0
    rep = _report(loaded, sim, info, result, cp, live, duration, cams, estimates, emulator, wall_s)
    if recording is not None:
        recording["dropped"] += int(estimates.get("record_dropped", 0))
        rep["recording"] = recording
    return rep


def _scene_sim(loaded: Any) -> Any:
    """The scene built as ``hapticloud run`` builds it (here: the ground truth; raises if the
    scene is infeasible)."""
    from hapticloud.core.scene.assembly import assemble

    return assemble(loaded)


def _checked_scene(
    scene: str, overrides: dict[str, Any] | None, duration_s: float | None, emulator: str
) -> tuple[Any, Any, float]:
    """The loaded scene, its simulation and the session's duration, or a ConfigError."""
    from hapticloud.core.errors import ConfigError
    from hapticloud.core.limits import MAX_DURATION_S
    from hapticloud.core.scene import load_scene

    from ..control.process import EMULATOR_MODES, PERIOD_S

    if emulator not in EMULATOR_MODES:
        raise ConfigError(f"emulator = {emulator!r}: expected one of {', '.join(EMULATOR_MODES)}")
    loaded = load_scene(scene, overrides)
    sim = _scene_sim(loaded)
    cfg = loaded.config
    duration = cfg.scene.duration_s if duration_s is None else float(duration_s)
    if not (math.isfinite(duration) and duration > 0.0):
        raise ConfigError(f"duration = {duration}: must be a positive number of seconds")
    if duration > MAX_DURATION_S:
        raise ConfigError(f"duration = {duration:g}: must be at most {MAX_DURATION_S:g} s")
    if abs(cfg.loop.rate_hz - 1.0 / PERIOD_S) > 1e-6:
        raise ConfigError(
            f"loop.rate_hz = {cfg.loop.rate_hz:g}: the control process runs at {1 / PERIOD_S:g} Hz"
        )
    return loaded, sim, duration


def _control_process(
    scene: str,
    overrides: dict[str, Any] | None,
    emulator: str,
    fifo_priority: int | None,
    plant_substeps: int | None,
    duration: float,
) -> Any:
    """The control process (not started) with the scene's arm in the emulated drives."""
    from ..control.process import PERIOD_S, ControlProcess
    from ..drives.scene_arm import SceneArmFactory

    return ControlProcess(
        scene,
        overrides,
        emulator=emulator,
        fifo_priority=fifo_priority,
        dynamics=SceneArmFactory(scene, overrides, plant_substeps),
        log_ticks=int((duration + 10.0) / PERIOD_S),
    )


def _recorder(record: str | None, loaded: Any, limit_bytes: int | None) -> Any:
    """A recorder for ``record`` (a path), or ``None``."""
    if record is None:
        return None
    from ..recording.runs import scene_recorder

    return scene_recorder(record, loaded, "run --hardware", "monotonic", limit_bytes=limit_bytes)


class _LiveSession:
    """This process's side of the running session: enables it, then samples the HIP and drains
    the loop's snapshots (to the recorder too) until the scene's time is up."""

    def __init__(self, cp: Any, hip_radius_m: float, recorder: Any, say: Callable[[str], None]):
        self._cp = cp
        self._hip_radius_m = hip_radius_m
        self._recorder = recorder
        self._say = say
        self.sampler = _HipSampler(cp.robot_state)
        self.snaps: list[Any] = []
        self._waiter = _StateWaiter(cp, self.snaps)
        self.startup_faults: list[str] = []
        self.t_enabled = math.nan

    def enable(self) -> None:
        """READY (startup faults reset), then ENABLED; :attr:`t_enabled` is scene time 0."""
        self.startup_faults = self._waiter.ready(30.0)
        self._cp.enable("hapticloud run --hardware")
        self.t_enabled = self._waiter.wait((_ENABLED,), 5.0).t

    def _drain(self) -> None:
        fresh = self._cp.snapshots()
        self.snaps.extend(fresh)
        if self._recorder is not None:
            _record(self._recorder, fresh, self._hip_radius_m, self._say)

    def run(
        self, start_perception: Callable[[], Any] | None, duration: float, name: str
    ) -> tuple[dict[str, Any], dict[str, Any] | None, dict[str, Any] | None]:
        """Start the perception process (if any), enable, run ``duration`` s, stop everything
        (the recorder last); returns the perception's figures, the control process's result and
        the recording's."""
        perception = None
        estimates: dict[str, Any] = {}
        try:
            if start_perception is not None:
                perception = start_perception()
            self.enable()
            if perception is not None:
                perception.go(self.t_enabled)
            self._say(f"session enabled; running {duration:g} s of {name} in real time ...")
            self.run_for(duration)
        finally:
            try:
                if perception is not None:
                    estimates = _stop_perception(perception)
            finally:
                result = self._cp.stop(timeout=20.0)
                recording = self._recorder.close() if self._recorder is not None else None
        return estimates, result, recording

    def run_for(self, duration: float) -> None:
        """Until ``duration`` s after enable (then torque off) or the control process ends."""
        cp = self._cp
        t_end = self.t_enabled + duration
        next_report = self.t_enabled + 1.0
        next_drain = 0.0
        while True:
            now = time.monotonic()
            if now >= t_end or not cp.alive:
                if cp.alive:
                    cp.disable()  # torque off at the end of the scene, before the teardown
                break
            self.sampler.sample()
            if now >= next_drain:
                self._drain()
                next_drain = now + 0.05
            if now >= next_report:
                self._say(f"  t = {now - self.t_enabled:5.1f} s")
                next_report += 1.0
            time.sleep(0.001)
        self._drain()


def _record(
    recorder: Any, snaps: list[Any], hip_radius_m: float, say: Callable[[str], None]
) -> None:
    """The drained snapshots to the recorder; its alarms said (the session goes on)."""
    from ..recording.runs import record_snapshots

    record_snapshots(recorder.sink, snaps, hip_radius_m)
    for alarm in recorder.alarms():
        say(f"  {alarm}")


def _report(
    loaded: Any,
    sim: Any,
    info: Mapping[str, Any],
    result: Mapping[str, Any],
    cp: Any,
    live: _LiveSession,
    duration: float,
    cams: list[Any],
    estimates: dict[str, Any],
    emulator: str,
    wall_s: float,
) -> dict[str, Any]:
    from ..control.process import STATE_CODES

    codes = STATE_CODES
    snaps, t_enabled = live.snaps, live.t_enabled
    log = result["log"]
    state = log["state"]
    enabled = state == codes["enabled"]
    tau = log["tau_sent"]
    first_on = int(np.argmax(enabled)) if enabled.any() else len(state)
    d_proj = np.where(enabled, log["d_proj_m"], np.nan)
    truth, verdict, space = _truth(
        sim, live.sampler, t_enabled, log, enabled, d_proj, result, codes
    )
    return {
        "mode": HARDWARE_MODE,
        "scene": {
            "name": loaded.name,
            "path": loaded.path,
            "description": loaded.config.scene.description,
        },
        "duration_s": duration,
        "wall_time_s": wall_s,
        "emulator": emulator,
        "error": cp.error,
        "process": {
            k: info.get(k)
            for k in ("sched_fifo", "sched_note", "mlockall", "bus", "emulator_info", "cpu")
        },
        "hip_radius_m": sim.hip_radius_m,
        "patient": sim.patient is not None,
        "ticks": int(result["ticks"]),
        "enabled_ticks": int(enabled.sum()),
        "reached_enabled": bool(enabled.any()),
        "torque_before_enable_nm": float(np.abs(tau[:first_on]).max()) if first_on else 0.0,
        "control": _control_figures(result, enabled),
        "session": _session_figures(result, enabled, live.startup_faults),
        "haptics": _haptics_figures(log, enabled, d_proj),
        "estimates": _estimate_figures(estimates, cams, snaps),
        "truth": truth,
        "verdict": verdict.label,
        "space": space,
    }


def _truth(
    sim: Any,
    sampler: _HipSampler,
    t_enabled: float,
    log: Mapping[str, Any],
    enabled: Any,
    d_proj: Any,
    result: Mapping[str, Any],
    codes: Mapping[str, int],
) -> tuple[dict[str, Any], Verdict, dict[str, Any]]:
    """Ground truth from the sampled HIP, on the scene clock (0 = the enabled session's start),
    with the verdict and the space summary."""
    t = np.array(sampler.t)
    hips = np.array(sampler.hip).reshape(-1, 3)
    st = np.array(sampler.state)
    on = (st == codes["enabled"]) & (t >= t_enabled) if t.size else np.zeros(0, bool)
    ts = t[on] - t_enabled
    margins = np.array([sim.true_margin(h, float(s))[0] for h, s in zip(hips[on], ts, strict=True)])
    r = sim.hip_radius_m
    truth: dict[str, Any] = {"samples": int(margins.size)}
    if margins.size:
        k = int(np.argmin(margins))
        gaps = np.diff(ts)
        truth.update(
            {
                "sample_rate_hz": json_float(margins.size / max(ts[-1] - ts[0], 1e-9)),
                "largest_gap_ms": json_float(gaps.max() * 1e3) if gaps.size else None,
                "min_margin_m": json_float(margins[k]),
                "t_min_margin_s": json_float(ts[k]),
                "hip_at_min_m": [float(x) for x in hips[on][k]],
                "max_penetration_m": json_float(max(0.0, -float(margins[k]))),
                "min_center_margin_m": json_float(margins[k] + r),
            }
        )
        # The logged d_proj at the sample times: what the controller believed vs the truth.
        lt = log["t"]
        d_at = np.interp(t[on], lt, np.where(np.isfinite(d_proj), d_proj, np.nan))
        err = d_at - margins
        near = np.isfinite(err) & (margins < 0.05)
        truth["d_proj_minus_true_mm_near"] = _spread(np.abs(err[near]), 1e3) if near.any() else None
        step = max(1, margins.size // 2000)
        truth["series"] = {
            "t_s": [round(float(x), 4) for x in ts[::step]],
            "margin_m": [round(float(x), 6) for x in margins[::step]],
        }
    verdict, space = _verdict(log, enabled, t[on] if margins.size else t[:0], ts, margins, result)
    truth.update(verdict.to_json())
    return truth, verdict, space


def _control_figures(result: Mapping[str, Any], enabled: Any) -> dict[str, Any]:
    """The control loop's timing, deadline and bus figures."""
    log = result["log"]
    deadline = dict(result["deadline"])
    return {
        "misses": int(deadline.get("misses", 0)),
        "misses_per_10k": json_float(deadline.get("misses_per_10k")),
        "overruns": deadline.get("overruns"),
        "skipped": deadline.get("skipped"),
        "tick_us": _spread(log["tick_us"]),
        "tick_us_enabled": _spread(log["tick_us"][enabled]),
        "body_us": _spread(log["body_us"]),
        "lateness_us": _spread(log["lateness_us"]),
        "deadline": {k: v for k, v in deadline.items() if not isinstance(v, str)},
        "link_counters": dict(result["link_counters"]),
        "link_events": [list(e) for e in result["link_events"][-20:]],
        "emulator_events": [list(e) for e in result["emulator_events"][-20:]],
    }


def _session_figures(
    result: Mapping[str, Any], enabled: Any, startup_faults: list[str]
) -> dict[str, Any]:
    """The session's transitions, the faults reset before enable, the watchdogs' reactions."""
    reaction = result["log"]["reaction"][enabled]
    return {
        "transitions": [list(tr) for tr in result["transitions"]],
        "startup_faults_reset": list(startup_faults),
        "reactions": [list(rx) for rx in result["reactions"]],
        "reaction_ticks": {
            name: int((reaction == level).sum())
            for level, name in enumerate(("none", "hold_surface", "damping", "torque_off"))
        },
    }


def _haptics_figures(log: Mapping[str, Any], enabled: Any, d_proj: Any) -> dict[str, Any]:
    """What the haptic tick saw while enabled: closest d_proj, approach speeds, capped ticks."""
    approach = np.where(enabled, log["approach_mps"], np.nan)
    capped = enabled & np.isfinite(log["approach_limit_mps"])
    v_pos = approach[np.isfinite(approach)]
    return {
        "min_d_proj_m": json_float(np.nanmin(d_proj)) if np.isfinite(d_proj).any() else None,
        "approach_mps": {
            "max": json_float(v_pos.max()) if v_pos.size else None,
            "p99": json_float(np.percentile(v_pos, 99)) if v_pos.size else None,
            "median": json_float(np.median(v_pos)) if v_pos.size else None,
        },
        "approach_capped_ticks": int(capped.sum()),
    }


def _estimate_figures(
    estimates: dict[str, Any], cams: list[Any], snaps: list[Any]
) -> dict[str, Any]:
    """The perception process's figures with what the loop made of its estimates."""
    fused_valid = [bool(s.fused_valid) for s in snaps if s.state == "enabled"]
    est_age = np.array([s.estimate_age_s for s in snaps if s.state == "enabled"])
    out = dict(estimates)
    out.update(
        {
            "cameras": [c.spec.name for c in cams],
            "models": [c.spec.model for c in cams],
            "fused_valid_fraction": json_float(np.mean(fused_valid)) if fused_valid else None,
            "fused_valid_ever": any(fused_valid),
            "estimate_age_ms": _spread(est_age, 1e3),
            "snapshots": len(snaps),
        }
    )
    return out


def _verdict(
    log: Mapping[str, Any],
    enabled: Any,
    t_sample: Any,
    ts: Any,
    margins: Any,
    result: Mapping[str, Any],
) -> tuple[Verdict, dict[str, Any]]:
    """SAFE/UNSAFE from the sampled true margins, explained by the tick's space state then."""
    lt, code = log["t"], log["space"]
    space_at = code[np.clip(np.searchsorted(lt, t_sample, side="right") - 1, 0, None)]
    verdict = judge(ts, margins, space=space_at if lt.size else None)
    transitions = [
        SpaceTransition(float(t), SpaceState[label.upper()], why)
        for t, label, why in result.get("space_transitions", ())
    ]
    dt = float(np.median(np.diff(lt))) if lt.size > 1 else 0.00125
    return verdict, space_summary(lt[enabled], code[enabled], transitions, dt)


def summary_lines(rep: Mapping[str, Any]) -> list[str]:
    """A few human-readable lines of a :func:`run_session` report."""

    def mm(x: float | None) -> str:
        return "n/a" if x is None else f"{x * 1e3:+.1f} mm"

    c, tr, est = rep["control"], rep["truth"], rep["estimates"]
    sent = est.get("sent", {})
    trs = rep["session"]["transitions"]
    states = " -> ".join([trs[0][1], *(t[2] for t in trs)]) if trs else "no transitions"
    lines = [
        f"{rep['scene']['name']}: {rep['duration_s']:g} s {rep['mode']} ({rep['emulator']})",
        f"control: {rep['ticks']} ticks ({rep['enabled_ticks']} enabled), "
        f"misses {c['misses']} ({c['misses_per_10k'] or 0:.1f} per 10k), tick median "
        f"{c['tick_us']['median'] or 0:.0f} us, p99 {c['tick_us']['p99'] or 0:.0f} us",
        f"session: {states}; {len(rep['session']['reactions'])} watchdog reaction changes",
        f"estimates sent: {sum(sent.values())} "
        f"({', '.join(f'{k} {v}' for k, v in sent.items()) or 'no cameras'}), "
        f"fused surface valid {100 * (est['fused_valid_fraction'] or 0):.0f}% of the time",
        f"true min margin {mm(tr.get('min_margin_m'))} "
        f"(max penetration {mm(tr.get('max_penetration_m'))}), "
        f"min d_proj {mm(rep['haptics']['min_d_proj_m'])}",
    ]
    share, longest = rep["space"]["fraction"], rep["space"]["longest_unknown_s"]
    lines.append(
        f"space while enabled: known {share['known']:.0%}, holding {share['holding']:.0%}, "
        f"stopped {share['stopped']:.0%} (longest unknown {longest:.2f} s)"
    )
    resets = rep["session"].get("startup_faults_reset")
    if resets:
        lines.append(f"reset before enable: {'; '.join(resets)}")
    if rep.get("error"):
        lines.append(f"control process error: {rep['error']}")
    if rep.get("recording"):
        from ..recording.runs import recording_summary

        lines.append(recording_summary(rep["recording"]))
    lines.append(rep["truth"]["line"])
    return lines
