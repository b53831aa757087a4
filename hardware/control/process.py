"""The 800 Hz control loop in its own process: drive bus I/O, fusion, the haptic tick, session.

:class:`ControlProcess` starts one ``multiprocessing`` child (``spawn`` context, so nothing of the
parent's threads, locks or GUI comes along). The child builds the scene's
:class:`~hapticloud.core.loop.HapticLoop` and its :class:`~hapticloud.core.fusion.SurfaceFusion`
(through :class:`~hapticloud.core.sim.closed_loop.ClosedLoopSim`, as ``hapticloud run`` does),
a :class:`~..drives.link.DriveLink` and the six emulated drives on the other end of the bus, then
runs on absolute deadlines (:class:`~.deadline.DeadlineLoop`: SCHED_FIFO when permitted, gc
frozen, memory locked). One tick::

    fb = link.poll_feedback()                   # answers to the previous SYNC
    commands, estimates (non-blocking polls)    # enable, e-stop, faults; camera estimates -> fusion
    reaction = watchdogs.check(...)             # cameras, estimate age, feedback, heartbeat, bus
    fused = fusion.sample(t), marked invalid while a watchdog holds (approach capped at v_min)
    res = loop.tick(t, fb.position, fb.velocity, fused=fused)
    link.send_cycle(tau by session state and reaction, controlwords)  # command + SYNC
    robot state -> shared memory; every 8th tick a snapshot -> pipe (only if writable)

The drives run in their own process by default (``emulator="process"``, on a
:class:`~..drives.transport.SocketPairBus`), like real drives on their own hardware; ``"stepped"``
runs them in the tick right after the SYNC (deterministic: tests), ``"thread"`` on a thread of the
child with the bus timing model.

Parent -> child: a one-way pipe of small commands (``enable``, ``disable``, ``estop``,
``reset``, ``inject`` a fault, ``stop``) and a second one of camera estimates and frame times
(:attr:`ControlProcess.estimate_connection`, which a perception process may hold instead of the
parent). The loop reads what is there and never waits. Child -> parent: a one-way pipe of
:class:`ControlSnapshot` every ``snapshot_every`` ticks, written only when ``select`` says the pipe
is writable (snapshots are < 4 KiB, at most ``PIPE_BUF``, so such a write does not block); a
snapshot that does not fit is dropped and counted. The robot's state (HIP, q) is also written
every tick to a :class:`~.shared_state.RobotStateBlock` under a sequence lock, for perception to
crop around.

Reactions (:mod:`hapticloud.hardware.session.watchdogs`): HOLD_SURFACE makes the space unknown for
the tick's guard (:mod:`hapticloud.core.haptics.unknown`: the last surface held, moving and grown,
then a stop and position hold) and caps the approach speed at ``hold_v_min_m_s``; DAMPING adds
joint damping to that (the haptic tick's torque minus ``damping_nms`` times the joint velocities);
TORQUE_OFF (and every state but ENABLED) sends zero torque; the link itself also blocks torque to
any drive not in OPERATION ENABLED and clamps to the drive limits. Every tick is recorded (times,
torques sent, state, reaction level, distance, approach speed and its cap) and returned by
:meth:`ControlProcess.stop`, so tests assert reactions from the log, not from sleeping. SIGINT in
the child is an emergency stop.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import multiprocessing as mp
import os
import select
import signal
import time
import traceback
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ..drives.faults import FAULT_METHODS
from ..session.states import SessionState
from .deadline import DeadlineLoop, lock_memory
from .messages import (
    ESTIMATE_WIRE_FIELDS,
    ControlSnapshot,
    estimate_from_dict,
    estimate_from_wire,
    estimate_to_dict,
    estimate_to_wire,
    send_camera_frame,
    send_estimate,
)
from .slack import Slack

__all__ = [
    "EMULATOR_MODES",
    "ESTIMATE_WIRE_FIELDS",
    "FAULT_METHODS",
    "STATE_CODES",
    "ControlProcess",
    "ControlSnapshot",
    "estimate_from_dict",
    "estimate_from_wire",
    "estimate_to_dict",
    "estimate_to_wire",
    "send_camera_frame",
    "send_estimate",
]

PERIOD_S = 1.0 / 800.0
#: Where the emulated drives run (see :class:`ControlProcess`).
EMULATOR_MODES = ("process", "stepped", "thread")

#: Integer codes of the session states in the recorded log (``log["state"]``), by state value:
#: :attr:`SessionState.code <hapticloud.hardware.session.states.SessionState.code>`.
STATE_CODES = {state.value: state.code for state in SessionState}

_channels = itertools.count()


# ----- the child ---------------------------------------------------------------------------------
_LOG_FIELDS = (
    "t",
    "k",
    "lateness_us",
    "tick_us",
    "master_us",
    "control_us",
    "emulator_us",
    "state",
    "reaction",
    "any_fault",
    "complete",
    "d_proj_m",
    "approach_mps",
    "approach_limit_mps",
    "poll_us",
    "inputs_us",
    "send_us",
    "publish_us",
    "fusion_us",
    "body_us",
    "ahead_us",
    "ahead_frames",
    "space",
)
_MAX_EVENTS_PER_SNAPSHOT = 8
#: Ticks in a row a snapshot or a refit may wait for time left in the period (:mod:`.slack`).
_MAX_DEFER_TICKS = 8
#: Events kept for the snapshots while none gets out (a reader that stopped reading).
_MAX_PENDING_EVENTS = 256
#: Ticks of fault-reset controlwords a reset request sends (the drives clear on its rising edge).
_FAULT_RESET_TICKS = 8


def _writable(fd: int) -> bool:
    try:
        return bool(select.select((), (fd,), (), 0.0)[1])
    except (OSError, ValueError):
        return False


def _child_main(params: dict[str, Any], cmd_conn: Any, out_conn: Any, est_conn: Any) -> None:
    try:
        _run_child(params, cmd_conn, out_conn, est_conn)
    except BaseException:
        try:
            out_conn.send(("error", traceback.format_exc()))
        except Exception:
            pass


def _run_child(params: dict[str, Any], cmd_conn: Any, out_conn: Any, est_conn: Any) -> None:
    import can
    from hapticloud.core.fusion import SurfaceFusion
    from hapticloud.core.loop import admit, build_controller
    from hapticloud.core.robot.model import RobotModel
    from hapticloud.core.scene import load_scene
    from hapticloud.core.sim.closed_loop import ClosedLoopSim
    from hapticloud.core.threads import settle_numerics

    from ..drives import DriveBusConfig, DriveEmulator, DriveLink, DriveTarget, EmulatorConfig
    from ..drives.emulator_process import EmulatorHandle
    from ..drives.transport import SocketPairBus
    from ..session import ReactionLevel as L
    from ..session import (
        SessionStateMachine,
        WatchdogConfig,
        Watchdogs,
        apply_reaction,
    )
    from .shared_state import RobotStateBlock

    settle_numerics(1)
    estop_flag = [False]

    def _on_sigint(signum: int, frame: Any) -> None:
        estop_flag[0] = True

    signal.signal(signal.SIGINT, _on_sigint)

    period = float(params["period_s"])
    loaded = load_scene(params["scene"], params.get("overrides"))
    camera_specs = {c.name: c for c in loaded.cameras}
    if loaded.cameras:
        # The cameras are the parent's (perception runs outside the loop): the scene's own
        # simulated cameras would render inside the tick.
        loaded = loaded.with_overrides({f"cameras.{name}.model": "oracle" for name in camera_specs})
    sim = ClosedLoopSim(loaded)
    hloop = sim.loop
    robot = hloop.robot
    fusion = hloop.fusion
    model = RobotModel.load(loaded.config.robot.urdf or None)
    cfg = DriveBusConfig(cycle_rate_hz=1.0 / period).for_model(model)
    mode = params["emulator"]
    stepped = mode == "stepped"
    # One simulation clock for the simulated drives, their arm and the link: one period per
    # tick. A machine that cannot keep up then runs the simulation slower than real time (said
    # in every snapshot) instead of judging the simulator's own delay as lost drive feedback.
    sim_clock: Any = SimClock(time.monotonic()) if params.get("sim_clock") else time.monotonic
    wd_cfg = WatchdogConfig.from_dict(params["watchdogs"]) if params.get("watchdogs") else None
    wd = Watchdogs(wd_cfg)
    machine = SessionStateMachine(t=time.monotonic())
    emu = None
    emu_proc = None
    if mode == "process":
        master_bus = SocketPairBus(params["bus_socket"], channel="master")
        drive_bus = None
        emu_proc = EmulatorHandle(params["emulator_conn"])
        emu_proc.init(
            {
                "bus": cfg,
                "emulator": EmulatorConfig(model_bus_timing=bool(params["bus_timing"])),
                "urdf": loaded.config.robot.urdf or None,
                "q0": sim.q0,
                "fifo_priority": (
                    None if params["fifo_priority"] is None else params["fifo_priority"] - 10
                ),
                "dynamics": params.get("dynamics"),
            },
        )
        emu_proc.wait_ready()
    else:
        ecfg = EmulatorConfig(
            model_bus_timing=not stepped, drive_response_s=0.0 if stepped else 20e-6
        )
        channel = f"hapticloud-control-{os.getpid()}-{next(_channels)}"
        fd = can.CanProtocol.CAN_FD
        master_bus = can.Bus(interface="virtual", channel=channel, protocol=fd)
        drive_bus = can.Bus(
            interface="virtual", channel=channel, protocol=fd, preserve_timestamps=True
        )
        dynamics = params.get("dynamics")
        emu = DriveEmulator(
            drive_bus,
            cfg,
            ecfg,
            model=model,
            q0=sim.q0,
            dynamics=dynamics(model) if dynamics is not None else None,
            clock=sim_clock,
        )
    link = DriveLink(master_bus, cfg, clock=sim_clock)
    state_block = RobotStateBlock.attach(params["state_block"], robot.n_joints)
    n = link.n_drives
    zeros = np.zeros(n)
    damping = float(params["damping_nms"])
    cap = int(params["log_ticks"])
    # Filled, not just zeroed: every page is touched now, not on the first write in the loop.
    log = {f: np.full(cap, 0.0) for f in _LOG_FIELDS}
    log_tau = np.full((cap, n), 0.0)
    log_hip = np.full((cap, 3), 0.0)
    snap_every = int(params["snapshot_every"])
    out_fd = out_conn.fileno()
    dl = DeadlineLoop(period, spin_s=float(params["spin_s"]), fifo_priority=params["fifo_priority"])
    codes = {s: s.code for s in SessionState}
    try:
        # Start-up, outside the timed loop: NMT start, drives to READY TO SWITCH ON.
        if emu is not None:
            emu.step()
        link.start_nodes()
        if emu is not None:
            emu.step()

        def pump() -> None:
            time.sleep(period)
            if emu is not None:
                emu.step()

        link.run_sequence(DriveTarget.DISABLED, timeout_s=2.0, pump=pump)
        if mode == "thread" and emu is not None:
            emu.start()
        cpu = params.get("cpu")
        pinned = None
        if cpu is not None and hasattr(os, "sched_setaffinity"):
            try:
                os.sched_setaffinity(0, {int(cpu)})
                pinned = int(cpu)
            except (OSError, ValueError):
                pinned = None
        locked, lock_note = lock_memory() if params.get("lock_memory", True) else (False, "off")
        # Every path of the tick once, before the first deadline (the first solve allocates).
        hloop.warm_up(time.monotonic(), sim.q0, zeros)
        dl.start()
        out_conn.send(
            (
                "ready",
                {
                    "pid": os.getpid(),
                    "sched_fifo": dl.sched_fifo,
                    "sched_note": dl.sched_note,
                    "cpu": pinned,
                    "mlockall": locked,
                    "mlockall_note": lock_note,
                    "emulator": mode,
                    "emulator_info": emu_proc.info if emu_proc is not None else None,
                    "bus": "socketpair (CAN FD)" if mode == "process" else "virtual (CAN FD)",
                    "cameras": list(camera_specs),
                    "torque_limits_nm": [float(x) for x in link.torque_limits],
                },
            )
        )
        est_time = -math.inf  # capture time of the newest estimate received
        fed_estimates = False
        camera_last: dict[str, float] = {}
        fault_reset_ticks = 0
        reset_pending = False
        estimates_waiting = False
        seq = 0
        dropped = 0
        events_dropped = 0
        events: list[tuple[int, float, str, str]] = []
        pending_events: list[tuple[float, str, str]] = []
        last_tr: Any = None
        last_r: Any = None
        last_sp: Any = None
        min_d = math.inf
        tick_max = 0.0
        rate_t, rate_i, rate = time.monotonic(), 0, 0.0
        duration = params.get("duration_s")
        t_begin = time.monotonic()
        last_fb = None
        running = True
        i = 0
        # One poll() system call per tick tells which input pipe has data; Connection.poll()
        # would build a selector per call and per pipe (measurably slower in a cold tick).
        cmd_fd = cmd_conn.fileno()
        est_fd = est_conn.fileno()
        poller = select.poll()
        poller.register(cmd_fd, select.POLLIN)
        poller.register(est_fd, select.POLLIN)

        def handle(cmd: tuple[Any, ...], t: float) -> bool:
            nonlocal fault_reset_ticks, fusion, reset_pending
            name = cmd[0]
            if name == "stop":
                return False
            if name == "enable":
                machine.enable(t, cmd[1] if len(cmd) > 1 else "enable requested")
            elif name == "disable":
                machine.disable(t, "disable requested")
            elif name == "estop":
                machine.emergency_stop(t, cmd[1] if len(cmd) > 1 else "emergency stop")
            elif name == "reset":
                # Fault-reset controlwords go out for a few ticks first; the reset is decided
                # when the drives' fault bits have cleared, or refused once they are spent.
                fault_reset_ticks = _FAULT_RESET_TICKS
                reset_pending = True
            elif name == "configure":
                haptics_cfg, fusion_cfg = cmd[1], cmd[2]
                controller_cfg = cmd[3] if len(cmd) > 3 else None
                if controller_cfg is not None:
                    if machine.state is SessionState.ENABLED:
                        pending_events.append(
                            (t, "config", "controller change refused: disable the session first")
                        )
                    else:
                        # A new hierarchy, warmed up at once: this tick overruns (counted), with
                        # no torque flowing.
                        hloop.controller = build_controller(robot, controller_cfg, sim.walls)
                        hloop.warm_up(t, fb.position_rad, fb.velocity_rad_s)
                        pending_events.append((t, "config", "controller applied"))
                if haptics_cfg is not None:
                    hloop.configure(haptics_cfg)
                if fusion_cfg is not None and fusion is not None:
                    # A new window (SurfaceFusion has no in-place reconfiguration).
                    fusion = SurfaceFusion(fusion_cfg)
                    hloop.fusion = fusion
            elif name == "inject":
                if emu_proc is not None:
                    emu_proc.inject(cmd[1], cmd[2], cmd[3])
                elif emu is not None:
                    _inject(emu.faults, cmd[1], cmd[2], cmd[3])
            detail = {"inject": cmd[1] if len(cmd) > 1 else ""}
            events.append((i, t, name, detail.get(name, "")))
            return True

        def take_estimates(t: float) -> bool:
            nonlocal est_time, fed_estimates
            added = False
            while True:
                try:
                    if not est_conn.poll():
                        break
                    kind, payload = est_conn.recv()
                except (EOFError, OSError):
                    # Perception's end closed: no more estimates (the watchdogs will say so).
                    poller.unregister(est_fd)
                    return added
                if kind == "camera":
                    name, t_frame = payload
                    camera_last[name] = max(camera_last.get(name, -math.inf), float(t_frame))
                    continue
                est = estimate_from_wire(payload)
                camera_last[est.camera] = max(camera_last.get(est.camera, -math.inf), est.t)
                fed_estimates = True
                spec = camera_specs.get(est.camera)
                min_q = spec.min_quality if spec is not None else 0.0
                fallbacks = spec.fuse_fallbacks if spec is not None else False
                # Any estimate is fresh news from perception, an invalid one too ("nothing within
                # the workspace sphere" is the normal case away from the patient): the estimate
                # watchdog watches perception's output, the fusion judges its validity.
                est_time = max(est_time, est.t)
                if fusion is not None and admit(est, min_q, fallbacks) and fusion.add(est):
                    added = True
            return added

        ahead = [0.0, 0]  # time (µs) and frames of the last read ahead
        # The snapshot and the refit wait for a tick with time left (at most 8 ticks, 10 ms):
        # after a long tick either would push the body past the next deadline.
        snap_slack = Slack(_MAX_DEFER_TICKS)
        refit_slack = Slack(_MAX_DEFER_TICKS)
        snap_due = False

        def read_ahead() -> None:
            # The drives answered the last SYNC during the period: their frames are decoded in
            # the spin before the deadline, and the tick reads only what came since.
            a0 = time.perf_counter()
            ahead[1] = link.read_pending()
            ahead[0] = (time.perf_counter() - a0) * 1e6

        while running:
            ahead[0], ahead[1] = 0.0, 0
            k, t_k = dl.wait(read_ahead)
            if sim_clock is not time.monotonic:
                sim_clock.advance(period)
            next_deadline = t_k + period
            p0 = time.perf_counter()
            t = time.monotonic()
            fb = link.poll_feedback()
            p_poll = time.perf_counter()
            # Commands and estimates from the parent(s): whatever is there, never waiting.
            for fd, _ in poller.poll(0):
                if fd == cmd_fd:
                    try:
                        while running and cmd_conn.poll():
                            running = handle(cmd_conn.recv(), t)
                    except (EOFError, OSError):
                        # The parent is gone: stop (torque off on the way out).
                        running = False
                        events.append((i, t, "stop", "parent gone"))
                else:
                    # Read and fused after this tick's command is out: a refit takes up to
                    # ~0.4 ms, and an estimate 33 ms apart loses nothing by one tick.
                    estimates_waiting = True
            if estop_flag[0]:
                estop_flag[0] = False
                machine.emergency_stop(t, "SIGINT")
                events.append((i, t, "estop", "SIGINT"))
            if duration is not None and t - t_begin >= duration:
                running = False
            state = machine.state
            drives_ok = fb.complete and not fb.any_stale and not fb.any_fault_bit
            if state is SessionState.DISCONNECTED:
                if drives_ok:
                    machine.connect(t, "drive feedback complete")
                    machine.drives_ready(t, "drives ready to switch on")
            else:
                # The session's heartbeat timeout decides (WatchdogConfig), from the age of the
                # oldest heartbeat; the link's shorter verdict is only an event in its log.
                reaction = wd.check(
                    t,
                    camera_last,
                    (t - est_time) if fed_estimates else 0.0,
                    fb.oldest_age_s,
                    False,
                    fb.any_fault_bit,
                    fb.bus_off,
                    heartbeat_age_s=fb.oldest_heartbeat_age_s,
                )
                apply_reaction(machine, reaction, t)
                # Decided once the causes cleared, or (refused) when the reset ticks are spent.
                if reset_pending and (wd.torque_off_cleared or fault_reset_ticks == 0):
                    ok, why = wd.reset(t)
                    machine.reset(t, cleared=ok, reason=why)
                    reset_pending = False
                if machine.state is SessionState.CONNECTED and drives_ok:
                    machine.drives_ready(t, "drives ready again")
            reaction = wd.reaction
            level = reaction.level
            fused = fusion.sample(t) if fusion is not None else None
            if level >= L.HOLD_SURFACE:
                # The watchdog distrusts the cameras: the space is unknown for the tick's guard
                # (the last surface held and grown, then a stop), approach capped at v_min.
                hloop.approach_limit_mps = wd.config.hold_v_min_m_s
                if fused is not None:
                    fused = dataclasses.replace(
                        fused, valid=False, reason=f"watchdog: {reaction.reason}", free_m=0.0
                    )
            else:
                hloop.approach_limit_mps = None
            p1 = time.perf_counter()
            res = hloop.tick(t, fb.position_rad, fb.velocity_rad_s, fused=fused)
            p2 = time.perf_counter()
            state = machine.state
            torque = state is SessionState.ENABLED and level < L.TORQUE_OFF
            if torque:
                target = DriveTarget.ENABLED
                if level >= L.DAMPING:
                    # The haptic tick on the held surface (approach capped at v_min) with the
                    # joint velocities damped on top: the arm comes to rest where it is and the
                    # held surface still stops it (damping alone would drop the constraint).
                    tau = res.tau - damping * fb.velocity_rad_s
                else:
                    tau = res.tau
            else:
                tau = zeros
                if fault_reset_ticks > 0:
                    fault_reset_ticks -= 1
                if state is SessionState.EMERGENCY_STOP:
                    target = DriveTarget.QUICK_STOP
                elif fault_reset_ticks > 0:
                    target = DriveTarget.FAULT_RESET
                else:
                    target = DriveTarget.DISABLED
            sent = link.send_cycle(tau, link.controlwords(target))
            p3 = time.perf_counter()
            if emu is not None and stepped:
                emu.step()
            p4 = time.perf_counter()
            d_now = float(res.d_proj_m)
            if d_now < min_d and state is SessionState.ENABLED:
                min_d = d_now
            hip_now = robot.hip_position()
            state_block.write(
                t,
                i,
                codes[state],
                int(level),
                hip_now,
                robot.hip_velocity(),
                fb.position_rad,
                fb.velocity_rad_s,
            )
            # Feedback in to command out (the stepped emulator's answer included): the tick.
            tick_us = (p4 - p0) * 1e6
            if tick_us > tick_max:
                tick_max = tick_us
            if i < cap:
                log["t"][i] = t
                log["k"][i] = k
                log["lateness_us"][i] = (p0 - (dl.t0 + k * period)) * 1e6
                log["tick_us"][i] = tick_us
                log["control_us"][i] = (p2 - p1) * 1e6
                log["emulator_us"][i] = (p4 - p3) * 1e6
                log["state"][i] = codes[state]
                log["reaction"][i] = int(level)
                log["any_fault"][i] = fb.any_fault_bit
                log["complete"][i] = fb.complete
                log["d_proj_m"][i] = d_now
                log["approach_mps"][i] = res.approach_mps
                lim = hloop.approach_limit_mps
                log["approach_limit_mps"][i] = math.nan if lim is None else lim
                log["poll_us"][i] = (p_poll - p0) * 1e6
                log["inputs_us"][i] = (p1 - p_poll) * 1e6
                log["send_us"][i] = (p3 - p2) * 1e6
                log["ahead_us"][i] = ahead[0]
                log["ahead_frames"][i] = ahead[1]
                log["space"][i] = res.space
                log_tau[i] = sent
                log_hip[i] = hip_now
            if i % snap_every == 0:
                snap_due = True
            if snap_due and snap_slack.fits(next_deadline - time.perf_counter()):
                snap_due = False
                s0 = time.perf_counter()
                # Session and watchdog changes since the last snapshot that got out.
                last_tr = _collect(machine.log, last_tr, pending_events, "state", _state_text)
                last_r = _collect(wd.log, last_r, pending_events, "reaction", _reaction_text)
                last_sp = _collect(
                    hloop.guard.transitions, last_sp, pending_events, "space", _space_text
                )
                if _writable(out_fd):
                    seq += 1
                    load = fb.bus_load_since(last_fb) if last_fb is not None else math.nan
                    last_fb = fb
                    if t - rate_t >= 0.5:
                        rate = (i - rate_i) / (t - rate_t)
                        rate_t, rate_i = t, i
                    out_conn.send(
                        (
                            "snap",
                            ControlSnapshot(
                                seq,
                                i,
                                t,
                                state.value,
                                level.name,
                                reaction.source,
                                reaction.reason[:160],
                                tuple(fb.position_rad.tolist()),
                                tuple(fb.velocity_rad_s.tolist()),
                                tuple(sent.tolist()),
                                tuple(hip_now.tolist()),
                                _constraint_force(robot, sent),
                                d_now,
                                min_d,
                                float(res.approach_mps),
                                bool(res.fused_valid),
                                (t - est_time) if fed_estimates else math.nan,
                                tuple((c, t - v) for c, v in camera_last.items()),
                                tick_us,
                                tick_max,
                                rate,
                                dl.misses,
                                dropped,
                                load,
                                tuple(pending_events[:_MAX_EVENTS_PER_SNAPSHOT]),
                                hloop.guard.state.label,
                                hloop.guard.reason[:160],
                                (rate * period)
                                if sim_clock is not time.monotonic and rate > 0.0
                                else math.nan,
                            ),
                        )
                    )
                    # Oldest first; the rest go with the next snapshots.
                    del pending_events[:_MAX_EVENTS_PER_SNAPSHOT]
                    tick_max = 0.0
                else:
                    dropped += 1
                if len(pending_events) > _MAX_PENDING_EVENTS:
                    # Nobody reads the snapshots: keep the newest (the result keeps them all).
                    events_dropped += len(pending_events) - _MAX_PENDING_EVENTS
                    del pending_events[:-_MAX_PENDING_EVENTS]
                snap_slack.record(time.perf_counter() - s0)
            p5 = time.perf_counter()
            if estimates_waiting and refit_slack.fits(next_deadline - p5):
                estimates_waiting = False
                if take_estimates(t) and fusion is not None:
                    fusion.prepare()
                refit_slack.record(time.perf_counter() - p5)
            if i < cap:
                p_end = time.perf_counter()
                log["publish_us"][i] = (p5 - p4) * 1e6
                log["fusion_us"][i] = (p_end - p5) * 1e6
                # The whole body, publishing and fusion included: what the deadline sees.
                log["body_us"][i] = (p_end - p0) * 1e6
                log["master_us"][i] = (p4 - p0 - (p2 - p1) - (p4 - p3)) * 1e6
            i += 1
            dl.done()
    finally:
        dl.stop()
        if emu is not None and not stepped:
            emu.stop()
        # Leave the drives without torque.
        try:
            link.send_cycle(np.zeros(link.n_drives), link.controlwords(DriveTarget.DISABLED))
        except Exception:
            pass
        emu_events = emu_proc.stop() if emu_proc is not None else []
        master_bus.shutdown()
        if drive_bus is not None:
            drive_bus.shutdown()
        state_block.close()
    if emu is not None:
        emu_events = [tuple(e) for e in emu.events()][-256:]
    m = min(i, cap)
    stats = dl.stats().as_dict()
    _collect(machine.log, last_tr, pending_events, "state", _state_text)
    _collect(wd.log, last_r, pending_events, "reaction", _reaction_text)
    _collect(hloop.guard.transitions, last_sp, pending_events, "space", _space_text)
    out_conn.send(
        (
            "result",
            {
                "ticks": i,
                "deadline": stats,
                "link_counters": link.counters._asdict(),
                "link_events": [tuple(e) for e in link.pop_events()][-256:],
                "emulator_events": emu_events,
                "transitions": [
                    (tr.t, tr.from_state.value, tr.to_state.value, tr.reason) for tr in machine.log
                ],
                "reactions": [(r.tick, r.t, r.level.name, r.source, r.reason) for r in wd.log],
                "space_transitions": [
                    (tr.t, tr.state.label, tr.reason) for tr in hloop.guard.transitions
                ],
                "commands": events,
                "snapshots_sent": seq,
                "snapshots_dropped": dropped,
                # Changes no snapshot carried yet; the parent hands them on in one more snapshot.
                "pending_events": pending_events[-_MAX_PENDING_EVENTS:],
                "events_dropped": events_dropped,
                "deferred": {
                    name: {"deferred": sl.deferred, "forced": sl.forced}
                    for name, sl in (("snapshot", snap_slack), ("refit", refit_slack))
                },
                "log": {f: a[:m].copy() for f, a in log.items()}
                | {"tau_sent": log_tau[:m].copy(), "hip_m": log_hip[:m].copy()},
                "bus_schedule": _busy_per_cycle(cfg),
            },
        )
    )


def _state_text(tr: Any) -> str:
    return f"{tr.to_state.value}: {tr.reason}"


def _reaction_text(r: Any) -> str:
    return f"{r.level.name} {r.source}: {r.reason}"


class SimClock:
    """The simulated drives' time: advanced one control period per tick, read as a clock."""

    def __init__(self, t0: float) -> None:
        self.t = float(t0)

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt


def _space_text(tr: Any) -> str:
    return f"{tr.state.label}: {tr.reason}" if tr.reason else tr.state.label


def _collect(
    log: tuple[Any, ...],
    last: Any,
    into: list[tuple[float, str, str]],
    kind: str,
    text: Callable[[Any], str],
) -> Any:
    """Append the entries of ``log`` after ``last`` to ``into`` as ``(t, kind, text)`` (text cut
    to 160 characters); returns the new ``last``."""
    if not log or log[-1] is last:
        return last
    for entry in _after(log, last):
        into.append((entry.t, kind, text(entry)[:160]))
    return log[-1]


def _after(log: tuple[Any, ...], last: Any) -> list[Any]:
    """The entries of a bounded log after ``last`` (by identity), oldest first."""
    out = []
    for item in reversed(log):
        if item is last:
            break
        out.append(item)
    out.reverse()
    return out


_ZERO3 = np.zeros(3)
_ZERO3.setflags(write=False)


def _constraint_force(robot: Any, tau: np.ndarray) -> tuple[float, float, float]:
    """Cartesian force at the HIP for the torque beyond transparency, ``J^T f = tau - h``."""
    if not np.any(tau):
        return (0.0, 0.0, 0.0)
    jac = robot.hip_jacobian()
    f, *_ = np.linalg.lstsq(jac.T, tau - robot.nonlinear_effects(), rcond=None)
    if not np.isfinite(f).all():
        return (0.0, 0.0, 0.0)
    return (float(f[0]), float(f[1]), float(f[2]))


def _inject(faults: Any, method: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
    if method not in FAULT_METHODS:
        raise ValueError(f"fault method {method!r}: expected one of {', '.join(FAULT_METHODS)}")
    getattr(faults, method)(*args, **kwargs)


def _busy_per_cycle(cfg: Any) -> dict[str, float] | None:
    try:
        from ..drives import config_load

        load = config_load(cfg)
        return {"load": float(load.load), "busy_per_cycle_us": 1e6 * float(load.busy_per_cycle_s)}
    except Exception:
        return None


# ----- the parent's handle -----------------------------------------------------------------------
class ControlProcess:
    """Handle on the control process (parent side; never blocks on the loop).

    Parameters
    ----------
    scene
        Scene file or shipped name; its robot, walls, cameras and haptics configure the tick.
    overrides
        ``--set`` style overrides for the scene.
    period_s
        Control period (1/800 s).
    fifo_priority
        SCHED_FIFO priority to try in the child (``None``: do not try); falls back cleanly. The
        emulator process, if any, asks for 10 less.
    spin_s
        Spin before each deadline (s).
    emulator
        Where the six emulated drives run: ``"process"`` (their own process, on a
        :class:`~..drives.transport.SocketPairBus`, like real drives: the default),
        ``"stepped"`` (in the loop right after the SYNC: deterministic, for tests; the tick then
        includes the drives' work) or ``"thread"`` (a thread of the control process, with the
        bus timing model; it competes for the loop's GIL).
    snapshot_every
        Publish a :class:`ControlSnapshot` every this many ticks (8: 100 Hz).
    log_ticks
        Ticks recorded for :meth:`stop`'s log (the first ones).
    duration_s
        Stop on its own after this long (s of the child's clock); ``None``: on :meth:`stop`.
    cpu
        Pin the loop to this CPU (``None``: no pinning; a refused pin is ignored).
    watchdogs
        :class:`~..session.WatchdogConfig` fields to override (``{"camera_timeout_s": 0.2}``).
    damping_nms
        Joint damping of the DAMPING reaction (N m s/rad).
    dynamics
        ``None`` (rigid arm) or a picklable callable ``model -> ArmDynamics`` for the emulated
        arm (e.g. one with a simulated patient pushing the handle).
    bus_timing
        With ``emulator="process"``: the drives release each answer at its modelled end of frame
        on the bus (about 8 wake-ups per cycle, a quarter of a core here) or, ``False``, all at
        once right after the SYNC (one wake-up; what the app uses to leave the CPU to the view).
    """

    def __init__(
        self,
        scene: str = "impacts",
        overrides: Mapping[str, Any] | None = None,
        *,
        period_s: float = PERIOD_S,
        fifo_priority: int | None = 80,
        spin_s: float = 200e-6,
        emulator: str = "process",
        snapshot_every: int = 8,
        log_ticks: int = 1 << 16,
        duration_s: float | None = None,
        cpu: int | None = None,
        watchdogs: Mapping[str, Any] | None = None,
        damping_nms: float = 2.0,
        dynamics: Any = None,
        bus_timing: bool = True,
        sim_clock: bool = False,
    ) -> None:
        if emulator not in EMULATOR_MODES:
            raise ValueError(
                f"emulator = {emulator!r}: expected one of {', '.join(EMULATOR_MODES)}"
            )
        if sim_clock and emulator != "stepped":
            raise ValueError("sim_clock: only with emulator = 'stepped' (simulated drives)")
        if not (math.isfinite(damping_nms) and damping_nms >= 0.0):
            raise ValueError(f"damping_nms = {damping_nms}: must be >= 0")
        if watchdogs:
            from ..session import WatchdogConfig

            WatchdogConfig.from_dict(dict(watchdogs))  # refuse a bad one here, not in the child
        self._params = {
            "scene": scene,
            "overrides": dict(overrides) if overrides else None,
            "period_s": float(period_s),
            "fifo_priority": fifo_priority,
            "spin_s": float(spin_s),
            "emulator": emulator,
            "snapshot_every": max(1, int(snapshot_every)),
            "log_ticks": int(log_ticks),
            "duration_s": duration_s,
            "cpu": cpu,
            "watchdogs": dict(watchdogs) if watchdogs else None,
            "damping_nms": float(damping_nms),
            "dynamics": dynamics,
            "bus_timing": bool(bus_timing),
            "sim_clock": bool(sim_clock),
        }
        self._ctx = mp.get_context("spawn")
        self._proc: Any = None
        self._cmd: Any = None
        self._out: Any = None
        self._est: Any = None
        self._block: Any = None
        self._emu_proc: Any = None
        self._snaps: list[ControlSnapshot] = []
        self._latest: ControlSnapshot | None = None
        self.info: dict[str, Any] | None = None
        self.result: dict[str, Any] | None = None
        self.error: str | None = None

    # ----- life cycle ---------------------------------------------------------------------------
    def start(self, timeout: float = 60.0) -> dict[str, Any]:
        """Start the child and wait until its loop runs; returns its start-up info."""
        if self._proc is not None:
            raise RuntimeError("control process already started")
        from .shared_state import RobotStateBlock

        cmd_r, cmd_w = self._ctx.Pipe(duplex=False)
        out_r, out_w = self._ctx.Pipe(duplex=False)
        est_r, est_w = self._ctx.Pipe(duplex=False)
        self._block = RobotStateBlock.create()
        params = dict(self._params, state_block=self._block.name)
        ends: tuple[Any, ...] = ()
        if params["emulator"] == "process":
            from ..drives.emulator_process import spawn_emulator
            from ..drives.transport import socket_pair

            bus_master, bus_drives = socket_pair()
            self._emu_proc, emu_conn = spawn_emulator(bus_drives)
            params["bus_socket"], params["emulator_conn"] = bus_master, emu_conn
            ends = (bus_master, bus_drives, emu_conn)
        self._proc = self._ctx.Process(
            target=_child_main,
            args=(params, cmd_r, out_w, est_r),
            name="hapticloud-control",
            daemon=True,
        )
        self._proc.start()
        for end in (cmd_r, out_w, est_r, *ends):
            end.close()
        self._cmd, self._out, self._est = cmd_w, out_r, est_w
        end_t = time.monotonic() + timeout
        while self.info is None and self.error is None:
            if self._out.poll(0.1):
                self._pump_one()
                continue
            if not self._proc.is_alive():
                self._pump()
                if self.info is None and self.error is None:
                    self.error = f"exit code {self._proc.exitcode}"
                break
            if time.monotonic() > end_t:
                self.stop(1.0)
                raise TimeoutError("control process did not start in time")
        if self.info is None:
            err = self.error
            self.stop(1.0)
            raise RuntimeError(f"control process failed at start-up:\n{err}")
        return self.info

    def _pump_one(self) -> None:
        try:
            kind, payload = self._out.recv()
        except (EOFError, OSError):
            if self.error is None and self.result is None:
                self.error = "the control process closed its pipe (it died)"
            return
        if kind == "snap":
            self._snaps.append(payload)
            if len(self._snaps) > 4096:
                del self._snaps[:-4096]
            self._latest = payload
        elif kind == "ready":
            self.info = payload
        elif kind == "result":
            self.result = payload
            pending = payload.get("pending_events")
            if pending and self._latest is not None:
                # The changes no snapshot carried, on a copy of the last one (the loop is over).
                last = self._latest._replace(seq=self._latest.seq + 1, events=tuple(pending))
                self._snaps.append(last)
                self._latest = last
        elif kind == "error":
            self.error = payload

    def _pump(self) -> None:
        if self._out is None:
            return
        try:
            while self._out.poll():
                self._pump_one()
        except (EOFError, OSError):
            pass

    def _send(self, *cmd: Any) -> None:
        if self._cmd is None:
            raise RuntimeError("control process not started")
        self._cmd.send(cmd)

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def stop(self, timeout: float = 10.0) -> dict[str, Any] | None:
        """Ask the loop to stop, collect its result (log and statistics), join the child."""
        if self._proc is None:
            return self.result
        end = time.monotonic() + timeout
        try:
            if self._proc.is_alive():
                self._send("stop")
        except (OSError, BrokenPipeError):
            pass
        while self.result is None and self.error is None:
            left = end - time.monotonic()
            if left <= 0:
                break
            try:
                if self._out.poll(min(left, 0.1)):
                    self._pump_one()
                elif not self._proc.is_alive():
                    self._pump()
                    break
            except (EOFError, OSError):
                break
        self._proc.join(max(0.0, end - time.monotonic()) + 1.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(2.0)
        for conn in (self._cmd, self._out, self._est):
            try:
                conn.close()
            except OSError:
                pass
        if self._block is not None:
            self._block.close()
        if self._emu_proc is not None:
            from ..drives.emulator_process import join_process

            join_process(self._emu_proc, 3.0)
            self._emu_proc = None
        self._proc = None
        self._cmd = self._out = self._est = self._block = None
        return self.result

    def __enter__(self) -> ControlProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ----- commands (non-blocking for the loop; the pipe buffers them) --------------------------
    def enable(self, reason: str = "enable requested") -> None:
        self._send("enable", reason)

    def disable(self) -> None:
        self._send("disable")

    def emergency_stop(self, reason: str = "emergency stop (API)") -> None:
        self._send("estop", reason)

    def reset(self) -> None:
        """Clear a FAULT or EMERGENCY_STOP (refused while a torque-off cause is still active)."""
        self._send("reset")

    def configure(self, *, haptics: Any = None, fusion: Any = None, controller: Any = None) -> None:
        """New :class:`~hapticloud.core.loop.HapticsConfig` and/or
        :class:`~hapticloud.core.fusion.FusionConfig` for the loop, applied at its next tick
        (validated configs only: they validate on construction); a new
        :class:`~hapticloud.core.control.ControllerConfig` only while the session is not
        ENABLED (rebuilding the hierarchy costs a few ms; refused otherwise, with an event)."""
        from hapticloud.core.control import ControllerConfig
        from hapticloud.core.fusion import FusionConfig
        from hapticloud.core.loop import HapticsConfig

        if controller is not None and not isinstance(controller, ControllerConfig):
            raise TypeError(
                f"controller: expected ControllerConfig, got {type(controller).__name__}"
            )
        if haptics is not None and not isinstance(haptics, HapticsConfig):
            raise TypeError(f"haptics: expected HapticsConfig, got {type(haptics).__name__}")
        if fusion is not None and not isinstance(fusion, FusionConfig):
            raise TypeError(f"fusion: expected FusionConfig, got {type(fusion).__name__}")
        self._send("configure", haptics, fusion, controller)

    def inject_fault(self, method: str, *args: Any, **kwargs: Any) -> None:
        """Call ``method`` of the drive emulator's :class:`~..drives.FaultInjector` (one of
        :data:`FAULT_METHODS`) at the start of the loop's next tick (tests, demos)."""
        if method not in FAULT_METHODS:
            raise ValueError(f"fault method {method!r}: expected one of {', '.join(FAULT_METHODS)}")
        self._send("inject", method, tuple(args), dict(kwargs))

    def inject_drive_fault(self, drive: int, **kwargs: Any) -> None:
        """Fault ``drive`` (:meth:`FaultInjector.inject_drive_fault`)."""
        self.inject_fault("inject_drive_fault", drive, **kwargs)

    def clear_drive_fault(self, drive: int) -> None:
        self.inject_fault("clear_drive_fault", drive)

    # ----- perception in ------------------------------------------------------------------------
    @property
    def estimate_connection(self) -> Any:
        """The write end of the estimates pipe: hand it to the perception process (picklable
        at spawn) and send with :func:`send_estimate` / :func:`send_camera_frame` there."""
        if self._est is None:
            raise RuntimeError("control process not started")
        return self._est

    def send_estimate(self, est: Any) -> None:
        """A camera's :class:`~hapticloud.core.perception.SurfaceEstimate` for the loop's fusion
        (also counts as that camera's frame for the camera watchdog)."""
        send_estimate(self.estimate_connection, est)

    def camera_frame(self, camera: str, t: float) -> None:
        """A frame from ``camera`` captured at ``t`` (time.monotonic) without an estimate."""
        send_camera_frame(self.estimate_connection, camera, t)

    # ----- observation --------------------------------------------------------------------------
    @property
    def state_block_name(self) -> str:
        """Name of the shared :class:`~.shared_state.RobotStateBlock` (attach from anywhere)."""
        if self._block is None:
            raise RuntimeError("control process not started")
        return self._block.name

    def robot_state(self) -> Any:
        """The loop's current :class:`~.shared_state.RobotState` (``None`` before a tick)."""
        return None if self._block is None else self._block.read()

    def snapshots(self) -> list[ControlSnapshot]:
        """Every snapshot received since the last call (non-blocking; the newest 4096)."""
        self._pump()
        out, self._snaps = self._snaps, []
        return out

    @property
    def latest(self) -> ControlSnapshot | None:
        self._pump()
        return self._latest
