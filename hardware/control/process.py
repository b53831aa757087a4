"""The 800 Hz control loop in its own process: drive bus I/O, the haptic tick, session, watchdogs.

:class:`ControlProcess` starts one ``multiprocessing`` child (``spawn`` context, so nothing of the
parent's threads, locks or GUI comes along). The child builds the scene's
:class:`~hapticloud.core.loop.HapticLoop` (as ``hapticloud bench loop`` does, through
:class:`~hapticloud.core.sim.closed_loop.ClosedLoopSim`), a :class:`~..drives.link.DriveLink` on
python-can's ``virtual`` CAN FD bus and the :class:`~..drives.emulator.DriveEmulator` of the six
drives on the other end of that bus, then runs on absolute deadlines
(:class:`~.deadline.DeadlineLoop`: SCHED_FIFO when permitted, gc frozen). One tick::

    fb = link.poll_feedback()                       # answers to the previous SYNC
    commands from the parent (non-blocking poll)    # enable, e-stop, surface, fault injection
    reaction = watchdogs.check(...)                 # -> session FAULT on TORQUE_OFF
    res = loop.tick(t, fb.position, fb.velocity, fused=latest surface)
    link.send_command(res.tau if ENABLED and no torque-off else 0, controlwords)
    link.send_sync()
    emulator.step()                                 # "stepped" mode: deterministic, same thread

The emulator runs either stepped in the loop right after the SYNC (``emulator="stepped"``, no bus
timing model: answers are ready for the next tick, deterministic) or live on its own thread in
the child (``emulator="thread"``, with the bus timing model; that thread competes for the GIL).

Parent -> child: a one-way pipe of small commands (``enable``, ``disable``, ``estop``,
``reset``, ``surface`` with a :class:`~hapticloud.core.fusion.FusedSurface`, ``fault``,
``stop``); the loop reads what is there and never waits. Child -> parent: a one-way pipe of
:class:`ControlSnapshot` every ``snapshot_every`` ticks, written only when ``select`` says the
pipe is writable (snapshots are < 1 KiB, below ``PIPE_BUF``, so such a write never blocks); a
snapshot that does not fit is dropped and counted. The loop never waits on a reader.

Torque leaves the link only while the session is ENABLED and the watchdogs are not at
TORQUE_OFF; the link itself additionally blocks torque to any drive not in OPERATION ENABLED and
clamps to the drive limits. Every tick is recorded (times, torques sent, session state, reaction
level, drive fault flag) and returned by :meth:`ControlProcess.stop`, so tests assert reactions
from the log, not from sleeping. SIGINT in the child is an emergency stop.
"""

from __future__ import annotations

import itertools
import math
import multiprocessing as mp
import os
import select
import signal
import time
import traceback
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from .deadline import DeadlineLoop

__all__ = ["STATE_CODES", "ControlProcess", "ControlSnapshot"]

PERIOD_S = 1.0 / 800.0

#: Integer codes of the session states in the recorded log (``log["state"]``).
STATE_CODES = {
    "disconnected": 0,
    "connected": 1,
    "ready": 2,
    "enabled": 3,
    "fault": 4,
    "emergency_stop": 5,
}

_channels = itertools.count()


class ControlSnapshot(NamedTuple):
    """What the control process publishes every ``snapshot_every`` ticks (small, picklable)."""

    seq: int
    tick: int
    t: float
    state: str
    reaction: str
    reaction_source: str
    q: tuple[float, ...]
    qd: tuple[float, ...]
    tau_sent: tuple[float, ...]
    d_proj_m: float
    tick_us: float
    misses: int
    dropped_snapshots: int
    bus_load: float


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
)


def _writable(fd: int) -> bool:
    try:
        return bool(select.select((), (fd,), (), 0.0)[1])
    except (OSError, ValueError):
        return False


def _lock_memory() -> tuple[bool, str]:
    """``mlockall(MCL_CURRENT | MCL_FUTURE)`` so the loop takes no page faults; never raises."""
    try:
        import ctypes
        import ctypes.util

        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        if libc.mlockall(1 | 2) != 0:
            return False, f"mlockall refused (errno {ctypes.get_errno()}); pages may fault"
    except (OSError, AttributeError) as exc:
        return False, f"mlockall unavailable ({exc})"
    return True, "mlockall(MCL_CURRENT | MCL_FUTURE)"


def _child_main(params: dict[str, Any], cmd_conn: Any, out_conn: Any) -> None:
    try:
        _run_child(params, cmd_conn, out_conn)
    except BaseException:
        try:
            out_conn.send(("error", traceback.format_exc()))
        except Exception:
            pass


def _run_child(params: dict[str, Any], cmd_conn: Any, out_conn: Any) -> None:
    import can
    from hapticloud.core.robot.model import RobotModel
    from hapticloud.core.scene import load_scene
    from hapticloud.core.sim.closed_loop import ClosedLoopSim

    from ..drives import DriveBusConfig, DriveEmulator, DriveLink, DriveTarget, EmulatorConfig
    from ..session import SessionState, SessionStateMachine, Watchdogs, apply_reaction

    estop_flag = [False]

    def _on_sigint(signum: int, frame: Any) -> None:
        estop_flag[0] = True

    signal.signal(signal.SIGINT, _on_sigint)

    period = float(params["period_s"])
    loaded = load_scene(params["scene"], params.get("overrides"))
    if loaded.cameras:
        loaded = loaded.with_overrides(
            {f"cameras.{c.name}.model": "oracle" for c in loaded.cameras}
        )
    sim = ClosedLoopSim(loaded)
    hloop = sim.loop
    model = RobotModel.load(loaded.config.robot.urdf or None)
    cfg = DriveBusConfig(cycle_rate_hz=1.0 / period).for_model(model)
    stepped = params["emulator"] == "stepped"
    ecfg = EmulatorConfig(model_bus_timing=not stepped, drive_response_s=0.0 if stepped else 20e-6)
    channel = f"hapticloud-control-{os.getpid()}-{next(_channels)}"
    fd = can.CanProtocol.CAN_FD
    master_bus = can.Bus(interface="virtual", channel=channel, protocol=fd)
    drive_bus = can.Bus(interface="virtual", channel=channel, protocol=fd, preserve_timestamps=True)
    link = DriveLink(master_bus, cfg)
    emu = DriveEmulator(drive_bus, cfg, ecfg, model=model, q0=sim.q0)
    machine = SessionStateMachine(t=time.monotonic())
    wd = Watchdogs()
    n = link.n_drives
    zeros = np.zeros(n)
    cap = int(params["log_ticks"])
    # Filled, not just zeroed: every page is touched now, not on the first write in the loop.
    log = {f: np.full(cap, 0.0) for f in _LOG_FIELDS}
    log_tau = np.full((cap, n), 0.0)
    snap_every = int(params["snapshot_every"])
    out_fd = out_conn.fileno()
    dl = DeadlineLoop(period, spin_s=float(params["spin_s"]), fifo_priority=params["fifo_priority"])
    try:
        # Start-up, outside the timed loop: NMT start, drives to READY TO SWITCH ON.
        emu.step()
        link.start_nodes()
        emu.step()

        def pump() -> None:
            time.sleep(period)
            emu.step()

        link.run_sequence(DriveTarget.DISABLED, timeout_s=2.0, pump=pump)
        if not stepped:
            emu.start()
        cpu = params.get("cpu")
        pinned = None
        if cpu is not None and hasattr(os, "sched_setaffinity"):
            try:
                os.sched_setaffinity(0, {int(cpu)})
                pinned = int(cpu)
            except (OSError, ValueError):
                pinned = None
        locked, lock_note = _lock_memory() if params.get("lock_memory", True) else (False, "off")
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
                    "emulator": params["emulator"],
                    "channel": channel,
                },
            )
        )
        fused = None
        surface_t = -math.inf
        fed_surfaces = False
        fault_reset_ticks = 0
        seq = 0
        dropped = 0
        events: list[tuple[int, float, str, str]] = []
        duration = params.get("duration_s")
        t_begin = time.monotonic()
        last_fb = None
        running = True
        i = 0
        while running:
            k, _ = dl.wait()
            p0 = time.perf_counter()
            t = time.monotonic()
            fb = link.poll_feedback()
            # Commands from the parent: whatever is there, never waiting.
            while cmd_conn.poll():
                try:
                    cmd = cmd_conn.recv()
                except (EOFError, OSError):
                    # The parent is gone: stop (torque off on the way out).
                    running = False
                    events.append((i, t, "stop", "parent gone"))
                    break
                name = cmd[0]
                if name == "stop":
                    running = False
                elif name == "enable":
                    machine.enable(t, cmd[1] if len(cmd) > 1 else "enable requested")
                elif name == "disable":
                    machine.disable(t, "disable requested")
                elif name == "estop":
                    machine.emergency_stop(t, cmd[1] if len(cmd) > 1 else "emergency stop")
                elif name == "reset":
                    ok, why = wd.reset(t)
                    machine.reset(t, cleared=ok, reason=why)
                    fault_reset_ticks = 8
                elif name == "surface":
                    fused = cmd[1]
                    surface_t = t
                    fed_surfaces = True
                elif name == "fault":
                    emu.faults.inject_drive_fault(int(cmd[1]), **cmd[2])
                elif name == "clear_fault":
                    emu.faults.clear_drive_fault(int(cmd[1]))
                events.append((i, t, name, "" if name != "surface" else "fused surface"))
            if estop_flag[0]:
                estop_flag[0] = False
                machine.emergency_stop(t, "SIGINT")
                events.append((i, t, "estop", "SIGINT"))
            if duration is not None and t - t_begin >= duration:
                running = False
            state = machine.state
            if state is SessionState.DISCONNECTED:
                if fb.complete and not fb.stale.any() and not fb.any_fault:
                    machine.connect(t, "drive feedback complete")
                    machine.drives_ready(t, "drives ready to switch on")
            else:
                fb_age = float(fb.age_s.max())
                est_age = (t - surface_t) if fed_surfaces else 0.0
                reaction = wd.check(
                    t,
                    {},
                    est_age,
                    fb_age,
                    bool(fb.heartbeat_lost.any()),
                    bool(fb.any_fault),
                    bool(fb.bus_off),
                )
                apply_reaction(machine, reaction, t)
            reaction = wd.reaction
            p1 = time.perf_counter()
            res = hloop.tick(t, fb.position_rad, fb.velocity_rad_s, fused=fused)
            p2 = time.perf_counter()
            state = machine.state
            torque = state is SessionState.ENABLED and not reaction.torque_off
            if torque:
                target = DriveTarget.ENABLED
                tau = res.tau
            else:
                tau = zeros
                if state is SessionState.EMERGENCY_STOP:
                    target = DriveTarget.QUICK_STOP
                elif fault_reset_ticks > 0:
                    target = DriveTarget.FAULT_RESET
                    fault_reset_ticks -= 1
                else:
                    target = DriveTarget.DISABLED
            sent = link.send_command(tau, link.controlwords(target))
            link.send_sync()
            p3 = time.perf_counter()
            if stepped:
                emu.step()
            p4 = time.perf_counter()
            if i < cap:
                log["t"][i] = t
                log["k"][i] = k
                log["lateness_us"][i] = (p0 - (dl.t0 + k * period)) * 1e6
                log["tick_us"][i] = (p4 - p0) * 1e6
                log["master_us"][i] = (p4 - p0 - (p2 - p1) - (p4 - p3)) * 1e6
                log["control_us"][i] = (p2 - p1) * 1e6
                log["emulator_us"][i] = (p4 - p3) * 1e6
                log["state"][i] = STATE_CODES[state.value]
                log["reaction"][i] = int(reaction.level)
                log["any_fault"][i] = fb.any_fault
                log["complete"][i] = fb.complete
                log_tau[i] = sent
            if i % snap_every == 0:
                if _writable(out_fd):
                    seq += 1
                    load = fb.bus_load_since(last_fb) if last_fb is not None else math.nan
                    last_fb = fb
                    out_conn.send(
                        (
                            "snap",
                            ControlSnapshot(
                                seq,
                                i,
                                t,
                                state.value,
                                reaction.level.name,
                                reaction.source,
                                tuple(fb.position_rad.tolist()),
                                tuple(fb.velocity_rad_s.tolist()),
                                tuple(sent.tolist()),
                                float(res.d_proj_m),
                                (p4 - p0) * 1e6,
                                dl._misses,
                                dropped,
                                load,
                            ),
                        )
                    )
                else:
                    dropped += 1
            i += 1
            dl.done()
    finally:
        dl.stop()
        if not stepped:
            emu.stop()
        # Leave the drives without torque.
        try:
            link.send_command(np.zeros(link.n_drives), link.controlwords(DriveTarget.DISABLED))
            link.send_sync()
        except Exception:
            pass
        master_bus.shutdown()
        drive_bus.shutdown()
    m = min(i, cap)
    stats = dl.stats().as_dict()
    out_conn.send(
        (
            "result",
            {
                "ticks": i,
                "deadline": stats,
                "link_counters": link.counters._asdict(),
                "emulator_events": [tuple(e) for e in emu.events()][-256:],
                "transitions": [
                    (tr.t, tr.from_state.value, tr.to_state.value, tr.reason) for tr in machine.log
                ],
                "reactions": [(r.tick, r.t, r.level.name, r.source, r.reason) for r in wd.log],
                "commands": events,
                "snapshots_sent": seq,
                "snapshots_dropped": dropped,
                "log": {f: a[:m].copy() for f, a in log.items()} | {"tau_sent": log_tau[:m].copy()},
                "bus_schedule": _busy_per_cycle(cfg),
            },
        )
    )


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
        Scene file or shipped name; its robot, walls and haptics configure the tick.
    overrides
        ``--set`` style overrides for the scene.
    period_s
        Control period (1/800 s).
    fifo_priority
        SCHED_FIFO priority to try in the child (``None``: do not try); falls back cleanly.
    spin_s
        Spin before each deadline (s).
    emulator
        ``"stepped"`` (in the loop, after the SYNC) or ``"thread"`` (live thread in the child).
    snapshot_every
        Publish a :class:`ControlSnapshot` every this many ticks (8: 100 Hz).
    log_ticks
        Ticks recorded for :meth:`stop`'s log (the first ones).
    duration_s
        Stop on its own after this long (s of the child's clock); ``None``: on :meth:`stop`.
    cpu
        Pin the loop to this CPU (``None``: no pinning; a refused pin is ignored).
    """

    def __init__(
        self,
        scene: str = "impacts",
        overrides: Mapping[str, Any] | None = None,
        *,
        period_s: float = PERIOD_S,
        fifo_priority: int | None = 80,
        spin_s: float = 200e-6,
        emulator: str = "stepped",
        snapshot_every: int = 8,
        log_ticks: int = 1 << 16,
        duration_s: float | None = None,
        cpu: int | None = None,
    ) -> None:
        if emulator not in ("stepped", "thread"):
            raise ValueError(f"emulator = {emulator!r}: expected 'stepped' or 'thread'")
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
        }
        self._ctx = mp.get_context("spawn")
        self._proc: Any = None
        self._cmd: Any = None
        self._out: Any = None
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
        cmd_r, cmd_w = self._ctx.Pipe(duplex=False)
        out_r, out_w = self._ctx.Pipe(duplex=False)
        self._proc = self._ctx.Process(
            target=_child_main,
            args=(self._params, cmd_r, out_w),
            name="hapticloud-control",
            daemon=True,
        )
        self._proc.start()
        cmd_r.close()
        out_w.close()
        self._cmd, self._out = cmd_w, out_r
        end = time.monotonic() + timeout
        while self.info is None and self.error is None:
            if self._out.poll(0.1):
                self._pump_one()
                continue
            if not self._proc.is_alive():
                self._pump()
                if self.info is None and self.error is None:
                    self.error = f"exit code {self._proc.exitcode}"
                break
            if time.monotonic() > end:
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
            return
        if kind == "snap":
            self._snaps.append(payload)
            self._latest = payload
        elif kind == "ready":
            self.info = payload
        elif kind == "result":
            self.result = payload
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
        for conn in (self._cmd, self._out):
            try:
                conn.close()
            except OSError:
                pass
        self._proc = None
        self._cmd = self._out = None
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
        self._send("reset")

    def send_surface(self, fused: Any) -> None:
        """A new :class:`~hapticloud.core.fusion.FusedSurface` for the tick (latest wins)."""
        self._send("surface", fused)

    def inject_drive_fault(self, drive: int, **kwargs: Any) -> None:
        """Tell the emulator's fault injector to fault ``drive`` (tests, demos)."""
        self._send("fault", drive, kwargs)

    def clear_drive_fault(self, drive: int) -> None:
        self._send("clear_fault", drive)

    # ----- observation --------------------------------------------------------------------------
    def snapshots(self) -> list[ControlSnapshot]:
        """Every snapshot received since the last call (non-blocking)."""
        self._pump()
        out, self._snaps = self._snaps, []
        return out

    @property
    def latest(self) -> ControlSnapshot | None:
        self._pump()
        return self._latest
