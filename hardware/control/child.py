"""The control process's body: set-up, then a deadline loop around :class:`~.tick.ControlTick`.

Set-up (outside the timed loop): the scene's haptic loop and fusion, the drive link and the
emulated drives on the other end of the bus (their own process, a thread, or stepped in the
tick), the shared robot-state block, NMT start and the drives to READY TO SWITCH ON, the CPU pin
and memory lock, one warm-up of every path of the haptic tick. Then, per tick::

    k, t_k = deadline.wait(read_ahead)        # the drives' answers decoded in the spin
    fb = link.poll_feedback()                 # answers to the previous SYNC
    commands -> tick.command (never waiting)  # enable, e-stop, reset, configure, faults
    tau, target = tick.step(t, fb)            # session, watchdogs, haptic tick, torque
    link.send_cycle(tau, controlwords(target))  # command + SYNC
    robot state -> shared memory; the log; a snapshot when due and the period has time left
    estimates -> tick.take_estimates          # after the send, when the period has time left

SIGINT is an emergency stop. The loop never waits on a pipe: it reads what is there (one
``poll`` system call per tick says which input pipe has data) and writes a snapshot only when
``select`` says the pipe is writable.
"""

from __future__ import annotations

import itertools
import os
import select
import signal
import time
import traceback
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..drives.faults import FAULT_METHODS
from ..drives.protocol import N_DRIVES
from ..session.states import SessionState
from .deadline import DeadlineLoop, lock_memory
from .messages import ChildFailed, ControlConfig, InjectFault, Ready, Result, Stop
from .slack import Slack
from .telemetry import MAX_DEFER_TICKS, MAX_PENDING_EVENTS, Publisher, TickLog

__all__ = ["ChildEnds", "SimClock", "child_main"]

_channels = itertools.count()
_STATE_CODES = {state: state.code for state in SessionState}


@dataclass(frozen=True)
class ChildEnds:
    """The child's ends of its pipes and resources (picklable at spawn)."""

    commands: Any
    out: Any
    estimates: Any
    #: Name of the shared :class:`~.shared_state.RobotStateBlock`.
    state_block: str
    #: With ``emulator="process"``: the master's bus socket and the emulator's command pipe.
    bus_socket: Any = None
    emulator_conn: Any = None


class SimClock:
    """The simulated drives' time: advanced one control period per tick, read as a clock."""

    def __init__(self, t0: float) -> None:
        self.t = float(t0)

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt


def child_main(config: ControlConfig, ends: ChildEnds) -> None:
    """The control process's entry point: run, and say why if it raised."""
    try:
        run_child(config, ends)
    except BaseException:
        try:
            ends.out.send(ChildFailed(traceback.format_exc()))
        except Exception:
            pass


def run_child(config: ControlConfig, ends: ChildEnds) -> None:
    from hapticloud.core.threads import settle_numerics

    settle_numerics(1)
    sigint = [False]

    def _on_sigint(signum: int, frame: Any) -> None:
        sigint[0] = True

    signal.signal(signal.SIGINT, _on_sigint)
    rig = _Rig(config, ends)
    refit_slack = Slack(MAX_DEFER_TICKS)
    try:
        ends.out.send(Ready(rig.start()))
        ticks = _loop(rig, _Inputs(ends, rig.tick), refit_slack, sigint)
    finally:
        emulator_events = rig.close()
    rig.publisher.collect_events()
    ends.out.send(Result(_result(rig, ticks, emulator_events, refit_slack)))


def build_scene(config: ControlConfig) -> tuple[Any, Any, dict[str, Any]]:
    """The scene, its assembled parts (the haptic loop, fusion, walls, q0) and its cameras by
    name."""
    from hapticloud.core.scene import load_scene
    from hapticloud.core.scene.assembly import assemble

    loaded = load_scene(config.scene, dict(config.overrides) if config.overrides else None)
    camera_specs = {c.name: c for c in loaded.cameras}
    if loaded.cameras:
        # The cameras are the parent's (perception runs outside the loop): the scene's own
        # simulated cameras would render inside the tick.
        loaded = loaded.with_overrides({f"cameras.{name}.model": "oracle" for name in camera_specs})
    return loaded, assemble(loaded), camera_specs


class _Rig:
    """What the loop runs on: the tick, the drive link and emulator, the log and the publisher."""

    def __init__(self, config: ControlConfig, ends: ChildEnds) -> None:
        from hapticloud.core.robot.model import RobotModel

        from ..drives import DriveBusConfig, DriveLink
        from .shared_state import RobotStateBlock
        from .tick import ControlTick

        self.config = config
        self.period = period = float(config.period_s)
        self.loaded, sim, self.camera_specs = build_scene(config)
        self.q0 = sim.q0
        model = RobotModel.load(self.loaded.config.robot.urdf or None)
        self.bus_config = DriveBusConfig(cycle_rate_hz=1.0 / period).for_model(model)
        self.stepped = config.emulator == "stepped"
        # One simulation clock for the simulated drives, their arm and the link: one period per
        # tick. A machine that cannot keep up then runs the simulation slower than real time
        # (said in every snapshot) instead of judging the simulator's own delay as lost drive
        # feedback.
        self.simulated = bool(config.sim_clock)
        self.clock: Any = SimClock(time.monotonic()) if self.simulated else time.monotonic
        self.tick = ControlTick(
            sim.loop,
            N_DRIVES,
            walls=sim.walls,
            camera_specs=self.camera_specs,
            watchdogs=config.watchdogs,
            damping_nms=config.damping_nms,
            t0=time.monotonic(),
            inject=self._inject,
        )
        self.emu: Any = None
        self.emu_proc: Any = None
        self.drive_bus: Any = None
        self._start_emulator(model, ends)
        self.link = DriveLink(self.master_bus, self.bus_config, clock=self.clock)
        self.state_block = RobotStateBlock.attach(ends.state_block, self.tick.robot.n_joints)
        self.log = TickLog(config.log_ticks, self.link.n_drives)
        self.deadline = DeadlineLoop(
            period, spin_s=float(config.spin_s), fifo_priority=config.fifo_priority
        )
        self.publisher = Publisher(
            ends.out, self.tick, config.snapshot_every, period, self.simulated
        )

    def _start_emulator(self, model: Any, ends: ChildEnds) -> None:
        import can

        from ..drives import DriveEmulator, EmulatorConfig
        from ..drives.emulator_process import EmulatorHandle
        from ..drives.transport import SocketPairBus

        config = self.config
        if config.emulator == "process":
            self.master_bus = SocketPairBus(ends.bus_socket, channel="master")
            self.emu_proc = EmulatorHandle(ends.emulator_conn)
            fifo = config.fifo_priority
            self.emu_proc.init(
                {
                    "bus": self.bus_config,
                    "emulator": EmulatorConfig(model_bus_timing=bool(config.bus_timing)),
                    "urdf": self.loaded.config.robot.urdf or None,
                    "q0": self.q0,
                    "fifo_priority": None if fifo is None else fifo - 10,
                    "dynamics": config.dynamics,
                },
            )
            self.emu_proc.wait_ready()
            return
        stepped = self.stepped
        ecfg = EmulatorConfig(
            model_bus_timing=not stepped, drive_response_s=0.0 if stepped else 20e-6
        )
        channel = f"hapticloud-control-{os.getpid()}-{next(_channels)}"
        fd = can.CanProtocol.CAN_FD
        self.master_bus = can.Bus(interface="virtual", channel=channel, protocol=fd)
        self.drive_bus = can.Bus(
            interface="virtual", channel=channel, protocol=fd, preserve_timestamps=True
        )
        dynamics = config.dynamics
        self.emu = DriveEmulator(
            self.drive_bus,
            self.bus_config,
            ecfg,
            model=model,
            q0=self.q0,
            dynamics=dynamics(model) if dynamics is not None else None,
            clock=self.clock,
        )

    def _inject(self, cmd: InjectFault) -> None:
        if self.emu_proc is not None:
            self.emu_proc.inject(cmd.method, cmd.args, dict(cmd.kwargs))
        elif self.emu is not None:
            if cmd.method not in FAULT_METHODS:
                raise ValueError(
                    f"fault method {cmd.method!r}: expected one of {', '.join(FAULT_METHODS)}"
                )
            getattr(self.emu.faults, cmd.method)(*cmd.args, **cmd.kwargs)

    def start(self) -> dict[str, Any]:
        """Drives to READY TO SWITCH ON, CPU pin, memory lock, warm-up, the deadlines started;
        returns the start-up facts (:class:`~.messages.Ready`)."""
        from ..drives import DriveTarget

        emu, link, config = self.emu, self.link, self.config
        if emu is not None:
            emu.step()
        link.start_nodes()
        if emu is not None:
            emu.step()

        def pump() -> None:
            time.sleep(self.period)
            if emu is not None:
                emu.step()

        link.run_sequence(DriveTarget.DISABLED, timeout_s=2.0, pump=pump)
        if config.emulator == "thread" and emu is not None:
            emu.start()
        pinned = None
        if config.cpu is not None and hasattr(os, "sched_setaffinity"):
            try:
                os.sched_setaffinity(0, {int(config.cpu)})
                pinned = int(config.cpu)
            except (OSError, ValueError):
                pinned = None
        locked, lock_note = lock_memory()
        # Every path of the tick once, before the first deadline (the first solve allocates).
        self.tick.loop.warm_up(time.monotonic(), self.q0, self.tick.zeros)
        dl = self.deadline
        dl.start()
        return {
            "pid": os.getpid(),
            "sched_fifo": dl.sched_fifo,
            "sched_note": dl.sched_note,
            "cpu": pinned,
            "mlockall": locked,
            "mlockall_note": lock_note,
            "emulator": config.emulator,
            "emulator_info": self.emu_proc.info if self.emu_proc is not None else None,
            "bus": "socketpair (CAN FD)" if config.emulator == "process" else "virtual (CAN FD)",
            "cameras": list(self.camera_specs),
            "torque_limits_nm": [float(x) for x in link.torque_limits],
        }

    def close(self) -> list[tuple[Any, ...]]:
        """Torque off, drives disabled, emulator and buses shut; returns the emulator's events."""
        from ..drives import DriveTarget

        self.deadline.stop()
        if self.emu is not None and not self.stepped:
            self.emu.stop()
        # Leave the drives without torque.
        try:
            link = self.link
            link.send_cycle(np.zeros(link.n_drives), link.controlwords(DriveTarget.DISABLED))
        except Exception:
            pass
        events = self.emu_proc.stop() if self.emu_proc is not None else []
        self.master_bus.shutdown()
        if self.drive_bus is not None:
            self.drive_bus.shutdown()
        self.state_block.close()
        if self.emu is not None:
            events = [tuple(e) for e in self.emu.events()][-256:]
        return events


class _Inputs:
    """The loop's input pipes: commands and estimates, read without waiting."""

    def __init__(self, ends: ChildEnds, tick: Any) -> None:
        self._cmd = ends.commands
        self._est = ends.estimates
        self._tick = tick
        self.cmd_fd = self._cmd.fileno()
        self._est_fd = self._est.fileno()
        # One poll() system call per tick tells which input pipe has data; Connection.poll()
        # would build a selector per call and per pipe (measurably slower in a cold tick).
        self.poller = select.poll()
        self.poller.register(self.cmd_fd, select.POLLIN)
        self.poller.register(self._est_fd, select.POLLIN)

    def commands(self, t: float, feedback: Any) -> bool:
        """Hand the waiting commands to the tick; ``False`` on a stop or when the parent is
        gone (the loop then ends, torque off on the way out)."""
        conn, tick = self._cmd, self._tick
        try:
            while conn.poll():
                cmd = conn.recv()
                if type(cmd) is Stop:
                    return False
                tick.command(cmd, t, feedback)
        except (EOFError, OSError):
            tick.note(t, "stop", "parent gone")
            return False
        return True

    def estimates(self) -> list[tuple[str, Any]]:
        """The waiting estimates and frame times (none more once perception's end closed)."""
        conn = self._est
        out = []
        while True:
            try:
                if not conn.poll():
                    break
                out.append(conn.recv())
            except (EOFError, OSError):
                # Perception's end closed: no more estimates (the watchdogs will say so).
                self.poller.unregister(self._est_fd)
                break
        return out


def _loop(rig: _Rig, inputs: _Inputs, refit_slack: Slack, sigint: list[bool]) -> int:
    """Tick on the deadlines until a stop, the parent gone or the duration; returns the ticks."""
    period, duration = rig.period, rig.config.duration_s
    dl, link, tick, log, pub = rig.deadline, rig.link, rig.tick, rig.log, rig.publisher
    poll_feedback, send_cycle, controlwords = link.poll_feedback, link.send_cycle, link.controlwords
    step, robot, write_state = tick.step, tick.robot, rig.state_block.write
    emu_step = rig.emu.step if rig.stepped and rig.emu is not None else None
    advance = rig.clock.advance if rig.simulated else None
    poll_inputs, cmd_fd = inputs.poller.poll, inputs.cmd_fd
    perf, mono, codes = time.perf_counter, time.monotonic, _STATE_CODES
    ahead = [0.0, 0]  # time (µs) and frames of the last read ahead

    def read_ahead() -> None:
        # The drives answered the last SYNC during the period: their frames are decoded in
        # the spin before the deadline, and the tick reads only what came since.
        a0 = perf()
        ahead[1] = link.read_pending()
        ahead[0] = (perf() - a0) * 1e6

    pub.start(mono())
    t_begin = mono()
    i, running, estimates_waiting = 0, True, False
    while running:
        ahead[0], ahead[1] = 0.0, 0
        k, t_k = dl.wait(read_ahead)
        if advance is not None:
            advance(period)
        next_deadline = t_k + period
        p0 = perf()
        t = mono()
        fb = poll_feedback()
        p_poll = perf()
        for fd, _ in poll_inputs(0):
            if fd == cmd_fd:
                running = inputs.commands(t, fb)
            else:
                # Read and fused after this tick's command is out: a refit takes up to
                # ~0.4 ms, and an estimate 33 ms apart loses nothing by one tick.
                estimates_waiting = True
        if sigint[0]:
            sigint[0] = False
            tick.emergency_stop(t, "SIGINT")
        if duration is not None and t - t_begin >= duration:
            running = False
        tau, target = step(t, fb)
        sent = send_cycle(tau, controlwords(target))
        p3 = perf()
        if emu_step is not None:
            emu_step()
        p4 = perf()
        code = codes[tick.state]
        hip = robot.hip_position()
        qd = fb.velocity_rad_s
        write_state(t, i, code, int(tick.level), hip, robot.hip_velocity(), fb.position_rad, qd)
        # Feedback in to command out (the stepped emulator's answer included): the tick.
        pub.record_tick((p4 - p0) * 1e6)
        lateness_us = (p0 - (dl.t0 + k * period)) * 1e6
        log.record(i, t, k, lateness_us, (p0, p_poll, p3, p4), tick, code, fb, ahead, sent, hip)
        pub.maybe_publish(i, t, next_deadline, fb, sent, hip, dl.misses)
        p5 = perf()
        if estimates_waiting and refit_slack.fits(next_deadline - p5):
            estimates_waiting = False
            tick.take_estimates(inputs.estimates())
            refit_slack.record(perf() - p5)
        log.finish(i, p0, p4, p5, perf())
        i += 1
        dl.done()
    return i


def _result(
    rig: _Rig, ticks: int, emulator_events: list[Any], refit_slack: Slack
) -> dict[str, Any]:
    tick, pub, link = rig.tick, rig.publisher, rig.link
    machine, wd = tick.machine, tick.watchdogs
    return {
        "ticks": ticks,
        "deadline": rig.deadline.stats().as_dict(),
        "link_counters": link.counters._asdict(),
        "link_events": [tuple(e) for e in link.pop_events()][-256:],
        "emulator_events": emulator_events,
        "transitions": [
            (tr.t, tr.from_state.value, tr.to_state.value, tr.reason) for tr in machine.log
        ],
        "reactions": [(r.tick, r.t, r.level.name, r.source, r.reason) for r in wd.log],
        "space_transitions": [
            (tr.t, tr.state.label, tr.reason) for tr in tick.loop.guard.transitions
        ],
        "commands": tick.events,
        "snapshots_sent": pub.seq,
        "snapshots_dropped": pub.dropped,
        # Changes no snapshot carried yet; the parent hands them on in one more snapshot.
        "pending_events": tick.pending_events[-MAX_PENDING_EVENTS:],
        "events_dropped": pub.events_dropped,
        "deferred": {
            name: {"deferred": sl.deferred, "forced": sl.forced}
            for name, sl in (("snapshot", pub.slack), ("refit", refit_slack))
        },
        "log": rig.log.arrays(ticks),
        "bus_schedule": _busy_per_cycle(rig.bus_config),
    }


def _busy_per_cycle(cfg: Any) -> dict[str, float] | None:
    try:
        from ..drives import config_load

        load = config_load(cfg)
        return {"load": float(load.load), "busy_per_cycle_us": 1e6 * float(load.busy_per_cycle_s)}
    except Exception:
        return None
