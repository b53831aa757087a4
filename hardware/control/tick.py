"""One control tick: session, watchdogs, estimates into the fusion, the haptic tick, the torque.

:class:`ControlTick` is the control process's logic without its process, bus or clock: every
input comes in as an argument (the time ``t``, the drives' feedback, the parent's commands, the
camera estimates and frame times) and what goes out is the torque and the drives' target, with
the tick's state kept in named fields (read by :mod:`.telemetry` for the log and the snapshots).
It is driven by :mod:`.child` at 800 Hz and by the tests with explicit times, like
:mod:`hapticloud.hardware.session.states`. One tick::

    tick.step(t, fb, commands)        # commands, session and watchdogs, the held surface,
                                      # the haptic tick, the torque by state and reaction
    ... the child sends (tau, target) ...
    tick.take_estimates(messages)     # after the send: frame times, admission, fusion refit

Reactions (:mod:`hapticloud.hardware.session.watchdogs`): HOLD_SURFACE makes the space unknown for
the haptic tick's guard (:mod:`hapticloud.core.haptics.unknown`: the last surface held, moving
and grown, then a stop and position hold) and caps the approach speed at ``hold_v_min_m_s``;
DAMPING adds joint damping to that (the haptic tick's torque minus ``damping_nms`` times the joint
velocities); TORQUE_OFF (and every state but ENABLED) sends zero torque, with the drives' target
QUICK_STOP in an emergency stop, FAULT_RESET for a few ticks after a reset request, DISABLED
otherwise.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from hapticloud.core.fusion import SurfaceFusion
from hapticloud.core.haptics.unknown import SpaceState
from hapticloud.core.loop import admit, build_controller

from ..drives.protocol import DriveTarget
from ..session.states import SessionState, SessionStateMachine
from ..session.watchdogs import ReactionLevel, WatchdogConfig, Watchdogs, apply_reaction
from .messages import (
    Configure,
    Disable,
    EmergencyStop,
    Enable,
    InjectFault,
    Reset,
    estimate_from_wire,
)

__all__ = ["FAULT_RESET_TICKS", "ControlTick"]

#: Ticks of fault-reset controlwords a reset request sends (the drives clear on its rising edge).
FAULT_RESET_TICKS = 8

_ENABLED = SessionState.ENABLED
_DISCONNECTED = SessionState.DISCONNECTED
_CONNECTED = SessionState.CONNECTED
_EMERGENCY_STOP = SessionState.EMERGENCY_STOP
_HOLD_SURFACE = ReactionLevel.HOLD_SURFACE
_DAMPING = ReactionLevel.DAMPING
_TORQUE_OFF = ReactionLevel.TORQUE_OFF


class ControlTick:
    """The control process's loop state and safety reactions, stepped with explicit times.

    Parameters
    ----------
    loop
        The scene's :class:`~hapticloud.core.loop.HapticLoop` (its robot, fusion and guard).
    n_drives
        Drives on the bus (the length of the torque vector).
    walls
        The scene's walls, for a controller rebuilt by :class:`~.messages.Configure`.
    camera_specs
        The scene's cameras by name (their estimate gate: ``min_quality``, ``fuse_fallbacks``).
    watchdogs
        The watchdogs' configuration (``None``: the defaults).
    damping_nms
        Joint damping of the DAMPING reaction (N m s/rad).
    t0
        The session's start time.
    inject
        Where an :class:`~.messages.InjectFault` goes (the drive emulator); ``None``: nowhere.
    timer
        Clock for the haptic tick's cost only (``control_started``/``control_ended``); no decision
        reads it.
    """

    def __init__(
        self,
        loop: Any,
        n_drives: int,
        *,
        walls: Sequence[Any] = (),
        camera_specs: Mapping[str, Any] | None = None,
        watchdogs: WatchdogConfig | None = None,
        damping_nms: float = 2.0,
        t0: float = 0.0,
        inject: Callable[[InjectFault], None] | None = None,
        timer: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.loop = loop
        self.robot = loop.robot
        self.fusion = loop.fusion
        self.walls = tuple(walls)
        self.camera_specs = dict(camera_specs or {})
        self.watchdogs = Watchdogs(watchdogs)
        self.machine = SessionStateMachine(t=t0)
        self.damping_nms = float(damping_nms)
        self.zeros = np.zeros(int(n_drives))
        self._inject = inject
        self._timer = timer
        self.ticks = 0
        """Ticks stepped (the index of the next one)."""
        self.est_time = -math.inf
        """Capture time of the newest estimate received."""
        self.fed_estimates = False
        self.camera_last: dict[str, float] = {}
        """Each camera's newest frame time (estimates and frame times)."""
        self.fault_reset_ticks = 0
        self.reset_pending = False
        self.min_d = math.inf
        """Smallest projected distance while ENABLED (m)."""
        self.events: list[tuple[int, float, str, str]] = []
        """The commands handled: ``(tick, t, name, detail)``."""
        self.pending_events: list[tuple[float, str, str]] = []
        """Changes for the next snapshots, oldest first: ``(t, kind, text)``."""
        # What the last step decided (telemetry reads these).
        self.state = self.machine.state
        self.reaction = self.watchdogs.reaction
        self.level = self.reaction.level
        self.result: Any = None
        self.tau = self.zeros
        self.target = DriveTarget.DISABLED
        self.d_now = math.nan
        self.control_started = 0.0
        self.control_ended = 0.0

    # ----- inputs ---------------------------------------------------------------------------
    def command(self, cmd: Any, t: float, feedback: Any) -> None:
        """Apply one of the parent's commands (all but :class:`~.messages.Stop`, the child's)."""
        machine = self.machine
        kind = type(cmd)
        if kind is Enable:
            machine.enable(t, cmd.reason)
        elif kind is Disable:
            machine.disable(t, cmd.reason)
        elif kind is EmergencyStop:
            machine.emergency_stop(t, cmd.reason)
        elif kind is Reset:
            # Fault-reset controlwords go out for a few ticks first; the reset is decided when
            # the drives' fault bits have cleared, or refused once they are spent.
            self.fault_reset_ticks = FAULT_RESET_TICKS
            self.reset_pending = True
        elif kind is Configure:
            self._configure(cmd, t, feedback)
        elif kind is InjectFault:
            if self._inject is not None:
                self._inject(cmd)
        else:
            raise TypeError(f"not a control command: {cmd!r}")
        self.events.append((self.ticks, t, cmd.name, cmd.method if kind is InjectFault else ""))

    def _configure(self, cmd: Configure, t: float, feedback: Any) -> None:
        loop = self.loop
        if cmd.controller is not None:
            if self.machine.state is _ENABLED:
                self.pending_events.append(
                    (t, "config", "controller change refused: disable the session first")
                )
            else:
                # A new hierarchy, warmed up at once: this tick overruns (counted), with no
                # torque flowing.
                loop.controller = build_controller(self.robot, cmd.controller, self.walls)
                loop.warm_up(t, feedback.position_rad, feedback.velocity_rad_s)
                self.pending_events.append((t, "config", "controller applied"))
        if cmd.haptics is not None:
            loop.configure(cmd.haptics)
        if cmd.fusion is not None and self.fusion is not None:
            # A new window (SurfaceFusion has no in-place reconfiguration).
            self.fusion = SurfaceFusion(cmd.fusion)
            loop.fusion = self.fusion

    def emergency_stop(self, t: float, reason: str) -> None:
        """An emergency stop from the process itself (SIGINT), logged with its reason."""
        self.machine.emergency_stop(t, reason)
        self.events.append((self.ticks, t, "estop", reason))

    def note(self, t: float, name: str, detail: str) -> None:
        """Log a command that did not come through :meth:`command` (the parent gone)."""
        self.events.append((self.ticks, t, name, detail))

    def take_estimates(self, messages: Iterable[tuple[str, Any]]) -> bool:
        """Frame times and estimates (the pipe's ``(kind, payload)``) into the watchdogs'
        view and, admitted, into the fusion, refitted once if any was added; ``True`` then."""
        camera_last = self.camera_last
        fusion = self.fusion
        specs = self.camera_specs
        added = False
        for kind, payload in messages:
            if kind == "camera":
                name, t_frame = payload
                camera_last[name] = max(camera_last.get(name, -math.inf), float(t_frame))
                continue
            est = estimate_from_wire(payload)
            camera_last[est.camera] = max(camera_last.get(est.camera, -math.inf), est.t)
            self.fed_estimates = True
            spec = specs.get(est.camera)
            min_q = spec.min_quality if spec is not None else 0.0
            fallbacks = spec.fuse_fallbacks if spec is not None else False
            # Any estimate is fresh news from perception, an invalid one too ("nothing within
            # the workspace sphere" is the normal case away from the patient): the estimate
            # watchdog watches perception's output, the fusion judges its validity.
            self.est_time = max(self.est_time, est.t)
            if fusion is not None and admit(est, min_q, fallbacks) and fusion.add(est):
                added = True
        if added:
            fusion.prepare()
        return added

    # ----- the tick -------------------------------------------------------------------------
    def step(self, t: float, feedback: Any, commands: Sequence[Any] = ()) -> tuple[Any, Any]:
        """One tick at ``t`` on the drives' ``feedback``: the commands first, then the session
        and watchdogs, the haptic tick on the (possibly held) surface, and the torque; returns
        ``(tau, target)`` for the drives (the rest of the tick is in this object's fields)."""
        for cmd in commands:
            self.command(cmd, t, feedback)
        self._supervise(t, feedback)
        wd = self.watchdogs
        reaction = self.reaction = wd.reaction
        level = self.level = reaction.level
        loop = self.loop
        fused = self.fusion.sample(t) if self.fusion is not None else None
        if level >= _HOLD_SURFACE:
            # The watchdog distrusts the cameras: the space is unknown for the tick's guard
            # (the last surface held and grown, then a stop), approach capped at v_min.
            loop.approach_limit_mps = wd.config.hold_v_min_m_s
            if fused is not None:
                fused = dataclasses.replace(
                    fused, valid=False, reason=f"watchdog: {reaction.reason}", free_m=0.0
                )
        else:
            loop.approach_limit_mps = None
        timer = self._timer
        self.control_started = timer()
        qd = feedback.velocity_rad_s
        res = self.result = loop.tick(t, feedback.position_rad, qd, fused=fused)
        self.control_ended = timer()
        state = self.state = self.machine.state
        tau, target = self._torque(state, level, res, feedback)
        d_now = self.d_now = float(res.d_proj_m)
        # The margin to the fused surface the tick knew; a held surface is grown toward the HIP
        # on purpose (unseen motion of the patient): its d_proj is a precaution, not a margin.
        if d_now < self.min_d and state is _ENABLED and res.space is SpaceState.KNOWN:
            self.min_d = d_now
        self.ticks += 1
        return tau, target

    def _supervise(self, t: float, fb: Any) -> None:
        machine = self.machine
        drives_ok = fb.complete and not fb.any_stale and not fb.any_fault_bit
        if machine.state is _DISCONNECTED:
            if drives_ok:
                machine.connect(t, "drive feedback complete")
                machine.drives_ready(t, "drives ready to switch on")
            return
        wd = self.watchdogs
        # The session's heartbeat timeout decides (WatchdogConfig), from the age of the oldest
        # heartbeat; the link's shorter verdict is only an event in its log.
        reaction = wd.check(
            t,
            self.camera_last,
            (t - self.est_time) if self.fed_estimates else 0.0,
            fb.oldest_age_s,
            False,
            fb.any_fault_bit,
            fb.bus_off,
            heartbeat_age_s=fb.oldest_heartbeat_age_s,
        )
        apply_reaction(machine, reaction, t)
        # Decided once the causes cleared, or (refused) when the reset ticks are spent.
        if self.reset_pending and (wd.torque_off_cleared or self.fault_reset_ticks == 0):
            ok, why = wd.reset(t)
            machine.reset(t, cleared=ok, reason=why)
            self.reset_pending = False
        if machine.state is _CONNECTED and drives_ok:
            machine.drives_ready(t, "drives ready again")

    def _torque(self, state: SessionState, level: ReactionLevel, res: Any, fb: Any) -> tuple:
        if state is _ENABLED and level < _TORQUE_OFF:
            target = DriveTarget.ENABLED
            if level >= _DAMPING:
                # The haptic tick on the held surface (approach capped at v_min) with the joint
                # velocities damped on top: the arm comes to rest where it is and the held
                # surface still stops it (damping alone would drop the constraint).
                tau = res.tau - self.damping_nms * fb.velocity_rad_s
            else:
                tau = res.tau
        else:
            tau = self.zeros
            if self.fault_reset_ticks > 0:
                self.fault_reset_ticks -= 1
            if state is _EMERGENCY_STOP:
                target = DriveTarget.QUICK_STOP
            elif self.fault_reset_ticks > 0:
                target = DriveTarget.FAULT_RESET
            else:
                target = DriveTarget.DISABLED
        self.tau = tau
        self.target = target
        return tau, target

    # ----- what the snapshots say -----------------------------------------------------------
    def estimate_age(self, t: float) -> float:
        """Age of the newest estimate at ``t`` (NaN before the first)."""
        return (t - self.est_time) if self.fed_estimates else math.nan
