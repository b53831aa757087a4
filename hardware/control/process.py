"""The 800 Hz control loop in its own process: the parent's handle.

:class:`ControlProcess` starts one ``multiprocessing`` child (``spawn`` context, so nothing of the
parent's threads, locks or GUI comes along) from one frozen :class:`~.messages.ControlConfig`.
The child (:mod:`.child`) builds the scene's :class:`~hapticloud.core.loop.HapticLoop` and its
:class:`~hapticloud.core.fusion.SurfaceFusion`, a :class:`~..drives.link.DriveLink` and the six
emulated drives on the other end of the bus, then runs on absolute deadlines
(:class:`~.deadline.DeadlineLoop`: SCHED_FIFO when permitted, gc frozen, memory locked) around
one :class:`~.tick.ControlTick` (session, watchdogs, the held surface, the haptic tick, the
torque by state and reaction; pure, tested without a process).

The drives run in their own process by default (``emulator="process"``, on a
:class:`~..drives.transport.SocketPairBus`), like real drives on their own hardware; ``"stepped"``
runs them in the tick right after the SYNC (deterministic: tests), ``"thread"`` on a thread of the
child with the bus timing model.

Parent -> child (:mod:`.messages`): a one-way pipe of commands (:class:`~.messages.Enable`,
:class:`~.messages.Disable`, :class:`~.messages.EmergencyStop`, :class:`~.messages.Reset`,
:class:`~.messages.Configure`, :class:`~.messages.InjectFault`, :class:`~.messages.Stop`) and a
second one of camera estimates and frame times (:attr:`ControlProcess.estimate_connection`, which
a perception process may hold instead of the parent). The loop reads what is there and never
waits. Child -> parent: a one-way pipe of :class:`ControlSnapshot` every ``snapshot_every`` ticks,
written only when ``select`` says the pipe is writable (snapshots are < 4 KiB, at most
``PIPE_BUF``, so such a write does not block); a snapshot that does not fit is dropped and
counted; :class:`~.messages.Ready` once, :class:`~.messages.Result` at the end. The robot's
state (HIP, q) is also written every tick to a :class:`~.shared_state.RobotStateBlock` under a
sequence lock, for perception to crop around.

Every tick is recorded (:mod:`.telemetry`: times, torques sent, state, reaction level, distance,
approach speed and its cap) and returned by :meth:`ControlProcess.stop`, so tests assert
reactions from the log, not from sleeping. SIGINT in the child is an emergency stop.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import time
from collections.abc import Mapping
from typing import Any

from ..drives.faults import FAULT_METHODS
from ..session.states import SessionState
from .child import ChildEnds, child_main
from .messages import (
    ChildFailed,
    Configure,
    ControlConfig,
    ControlSnapshot,
    Disable,
    EmergencyStop,
    Enable,
    InjectFault,
    Ready,
    Reset,
    Result,
    Stop,
    send_camera_frame,
    send_estimate,
)

__all__ = [
    "EMULATOR_MODES",
    "FAULT_METHODS",
    "PERIOD_S",
    "STATE_CODES",
    "ControlConfig",
    "ControlProcess",
    "ControlSnapshot",
    "send_camera_frame",
    "send_estimate",
]

PERIOD_S = 1.0 / 800.0
#: Where the emulated drives run (see :class:`ControlProcess`).
EMULATOR_MODES = ("process", "stepped", "thread")

#: Integer codes of the session states in the recorded log (``log["state"]``), by state value:
#: :attr:`SessionState.code <hapticloud.hardware.session.states.SessionState.code>`.
STATE_CODES = {state.value: state.code for state in SessionState}


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
        wd_config = None
        if watchdogs:
            from ..session import WatchdogConfig

            # Refused here, not in the child.
            wd_config = WatchdogConfig.from_dict(dict(watchdogs))
        self.config = ControlConfig(
            scene=scene,
            overrides=dict(overrides) if overrides else None,
            period_s=float(period_s),
            fifo_priority=fifo_priority,
            spin_s=float(spin_s),
            emulator=emulator,
            snapshot_every=max(1, int(snapshot_every)),
            log_ticks=int(log_ticks),
            duration_s=duration_s,
            cpu=cpu,
            watchdogs=wd_config,
            damping_nms=float(damping_nms),
            dynamics=dynamics,
            bus_timing=bool(bus_timing),
            sim_clock=bool(sim_clock),
        )
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
        child_ends = ChildEnds(cmd_r, out_w, est_r, self._block.name)
        ends: tuple[Any, ...] = ()
        if self.config.emulator == "process":
            from ..drives.emulator_process import spawn_emulator
            from ..drives.transport import socket_pair

            bus_master, bus_drives = socket_pair()
            self._emu_proc, emu_conn = spawn_emulator(bus_drives)
            child_ends = ChildEnds(
                cmd_r, out_w, est_r, self._block.name, bus_socket=bus_master, emulator_conn=emu_conn
            )
            ends = (bus_master, bus_drives, emu_conn)
        self._proc = self._ctx.Process(
            target=child_main,
            args=(self.config, child_ends),
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
            msg = self._out.recv()
        except (EOFError, OSError):
            if self.error is None and self.result is None:
                self.error = "the control process closed its pipe (it died)"
            return
        if type(msg) is ControlSnapshot:
            self._snaps.append(msg)
            if len(self._snaps) > 4096:
                del self._snaps[:-4096]
            self._latest = msg
        elif type(msg) is Ready:
            self.info = dict(msg.info)
        elif type(msg) is Result:
            self.result = result = dict(msg.result)
            pending = result.get("pending_events")
            if pending and self._latest is not None:
                # The changes no snapshot carried, on a copy of the last one (the loop is over).
                last = self._latest._replace(seq=self._latest.seq + 1, events=tuple(pending))
                self._snaps.append(last)
                self._latest = last
        elif type(msg) is ChildFailed:
            self.error = msg.traceback

    def _pump(self) -> None:
        if self._out is None:
            return
        try:
            while self._out.poll():
                self._pump_one()
        except (EOFError, OSError):
            pass

    def _send(self, cmd: Any) -> None:
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
                self._send(Stop())
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
        self._send(Enable(reason))

    def disable(self) -> None:
        self._send(Disable())

    def emergency_stop(self, reason: str = "emergency stop (API)") -> None:
        self._send(EmergencyStop(reason))

    def reset(self) -> None:
        """Clear a FAULT or EMERGENCY_STOP (refused while a torque-off cause is still active)."""
        self._send(Reset())

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
        self._send(Configure(haptics, fusion, controller))

    def inject_fault(self, method: str, *args: Any, **kwargs: Any) -> None:
        """Call ``method`` of the drive emulator's :class:`~..drives.FaultInjector` (one of
        :data:`FAULT_METHODS`) at the start of the loop's next tick (tests, demos)."""
        if method not in FAULT_METHODS:
            raise ValueError(f"fault method {method!r}: expected one of {', '.join(FAULT_METHODS)}")
        self._send(InjectFault(method, tuple(args), dict(kwargs)))

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
