"""Six emulated drives on a python-can bus: CiA 402 state machine, simulated arm, bus timing.

:class:`DriveEmulator` answers the master like the real drives would on the CAN FD bus of
:mod:`.protocol`:

- **NMT**: each drive boots (boot-up heartbeat), waits in PRE-OPERATIONAL for an NMT start and
  then sends heartbeats (NMT state) at the configured producer period.
- **Cycle**: on each SYNC a drive latches the last command frame if its cycle matches the SYNC
  counter (else it holds the previous command and says so in its feedback), runs one CiA 402
  transition on the controlword, checks its command timeout, and answers with a feedback frame:
  joint position and velocity sampled at the SYNC, the torque it applies from this SYNC on, its
  statusword and both counters.
- **Torque**: only in OPERATION ENABLED, clamped to the smaller of the drive's limit and the
  command's torque limit; QUICK STOP ACTIVE brakes with ``-quick_stop_damping * qd``; every other
  state applies none (with ``brake_when_disabled`` the joint is also held still).
- **Arm**: the applied torques drive a dynamics callback on a fixed time grid of one cycle
  period (``physics_substeps`` steps per period): by default :class:`RigidArm`
  (:meth:`RobotModel.forward_dynamics`, semi-implicit Euler, viscous joint friction, inelastic
  joint stops); the closed-loop simulator plugs its own callback with the same signature.
- **Bus timing**: every frame, the master's and the drives', occupies a modelled bus for its
  duration at the configured bit rates (:func:`.schedule.frame_duration_s`, worst-case
  stuffing), one after another; each answer is released (sent and timestamped) at the end of its
  frame on that modelled bus, plus any injected latency.
- **Faults** (:mod:`.faults`): frame loss, latency, drive faults (statusword fault bit + EMCY),
  heartbeat loss, silent drives, bus-off.

It runs in two ways. **Stepped** (tests): :meth:`DriveEmulator.step` processes everything pending
on the bus, advances the arm to the clock's time and sends what is due; with a fake clock the
whole exchange is deterministic, no thread and no sleep. **Live**: :meth:`DriveEmulator.start`
runs the same code on a named reader thread (python-can ``Notifier`` style) against
``time.monotonic``; it is also a ``can.Listener``.

Timestamps of the frames it sends are in the emulator's clock. Over the ``virtual`` interface
they survive only if the emulator's bus was opened with ``preserve_timestamps=True``.
"""

from __future__ import annotations

import heapq
import math
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, NamedTuple, Protocol

import can
import numpy as np
from hapticloud.core.config import StageConfig, param
from hapticloud.core.errors import InputError
from hapticloud.core.robot.model import RobotModel
from hapticloud.core.validation import read_only
from numpy.typing import ArrayLike, NDArray

from . import codec
from . import protocol as p
from .config import DriveBusConfig
from .faults import FaultInjector
from .protocol import DriveState, EmcyCode, NmtCommand, NmtState
from .schedule import frame_duration_s

FloatArray = NDArray[np.float64]
Clock = Callable[[], float]

_ENABLED_OR_BRAKING = (DriveState.OPERATION_ENABLED, DriveState.QUICK_STOP_ACTIVE)
_FAULTY = (DriveState.FAULT_REACTION_ACTIVE, DriveState.FAULT)


class ArmDynamics(Protocol):
    """One integration step of the arm: ``(q, qd, tau, dt) -> (q_next, qd_next)``.

    ``q`` (rad), ``qd`` (rad/s), ``tau`` (N m, the drives' applied torques), ``dt`` (s); arrays of
    shape (6,). The callback must not keep references to its inputs.
    """

    def __call__(
        self, q: FloatArray, qd: FloatArray, tau: FloatArray, dt: float
    ) -> tuple[FloatArray, FloatArray]: ...


class RigidArm:
    """Default arm dynamics: rigid bodies of :class:`RobotModel` (ABA), semi-implicit Euler.

    Viscous joint friction ``-damping * qd``; at a joint limit the joint stops (position clipped,
    velocity into the limit zeroed): an inelastic end stop.

    Parameters
    ----------
    model
        Robot model (its own simulator work space is used; do not share across threads).
    damping_nms
        Viscous friction per joint (N m s/rad).
    """

    def __init__(self, model: RobotModel, damping_nms: float = 0.05) -> None:
        self._model = model
        self._damping = float(damping_nms)
        self._q_min = np.array(model.q_min)
        self._q_max = np.array(model.q_max)

    def __call__(
        self, q: FloatArray, qd: FloatArray, tau: FloatArray, dt: float
    ) -> tuple[FloatArray, FloatArray]:
        qdd = self._model.forward_dynamics(q, qd, tau - self._damping * qd)
        qd_next = qd + dt * qdd
        q_next = q + dt * qd_next
        low = q_next < self._q_min
        high = q_next > self._q_max
        if low.any() or high.any():
            q_next = np.clip(q_next, self._q_min, self._q_max)
            qd_next[low & (qd_next < 0.0)] = 0.0
            qd_next[high & (qd_next > 0.0)] = 0.0
        return q_next, qd_next


@dataclass(frozen=True)
class EmulatorConfig(StageConfig):
    """Behaviour of the emulated drives and arm (the bus itself is :class:`DriveBusConfig`)."""

    _path: ClassVar[str] = "emulator"

    model_bus_timing: bool = param(
        True, doc="release each answer at its modelled end of frame on the bus (else at once)"
    )
    drive_response_s: float = param(
        20e-6, lo=0.0, hi=0.01, unit="s", doc="end of SYNC to the drive's feedback being ready"
    )
    command_timeout_s: float = param(
        0.005,
        lo=0.0005,
        hi=1.0,
        unit="s",
        doc="an enabled drive without a fresh command for this long faults (EMCY 0x8250)",
    )
    joint_damping_nms: float = param(
        0.05, lo=0.0, hi=50.0, unit="N m s/rad", doc="viscous joint friction of the default arm"
    )
    quick_stop_damping_nms: float = param(
        5.0, lo=0.0, hi=500.0, unit="N m s/rad", doc="braking gain in QUICK STOP ACTIVE"
    )
    brake_when_disabled: bool = param(
        True, doc="hold a joint still while its drive applies no torque (the arm does not drop)"
    )
    physics_substeps: int = param(1, lo=1, hi=50, doc="integration steps per cycle period")
    max_catch_up_s: float = param(
        0.1, lo=0.001, hi=10.0, unit="s", doc="a longer gap in time is skipped, not integrated"
    )
    auto_start: bool = param(False, doc="drives go OPERATIONAL without an NMT start")


_STALL_REPORT_S = 0.005
"""A gap longer than this between two wake-ups of the drives' thread is logged as a ``stall``."""


class EmulatorEvent(NamedTuple):
    """Something an emulated drive did: ``kind`` is ``"state"`` (``detail``: new state name),
    ``"fault"`` (``detail``: error code), ``"nmt"`` (new NMT state), ``"command_timeout"``,
    ``"physics_skip"`` or ``"stall"`` (the drives' thread did not run for ``detail``, more than
    5 ms); ``t`` in the emulator's clock, ``drive`` -1 for the whole emulator."""

    t: float
    drive: int
    kind: str
    detail: str


@dataclass(frozen=True, eq=False)
class EmulatorState:
    """Snapshot of the emulated drives and arm (arrays read-only, shape (6,))."""

    t: float
    q: FloatArray
    qd: FloatArray
    #: Torque each drive applies now (N m).
    tau_nm: FloatArray
    #: Target torque each drive has latched (N m).
    target_nm: FloatArray
    state: tuple[DriveState, ...]
    nmt: tuple[NmtState, ...]
    syncs: int
    commands_missed: tuple[int, ...]


class DriveEmulator(can.Listener):
    """Six CiA 402 CST drives and the arm they move, on a python-can bus.

    Parameters
    ----------
    bus
        The drives' side of the bus (e.g. a second ``virtual`` bus on the master's channel).
    config
        Bus parameters, the same the master's :class:`~.link.DriveLink` uses.
    emulator
        Drive and arm behaviour.
    dynamics
        Arm dynamics callback (:class:`ArmDynamics`); default :class:`RigidArm` of ``model``.
    model
        Robot model for the default dynamics and the initial configuration (loaded if needed).
    q0
        Initial joint positions (rad); default ``model.q_home``.
    faults
        Fault injector (a fresh one without faults by default).
    clock
        Time source (s). Stepped tests pass a fake clock; the live thread needs real time.
    """

    def __init__(
        self,
        bus: can.BusABC,
        config: DriveBusConfig | None = None,
        emulator: EmulatorConfig | None = None,
        *,
        dynamics: ArmDynamics | None = None,
        model: RobotModel | None = None,
        q0: ArrayLike | None = None,
        faults: FaultInjector | None = None,
        clock: Clock = time.monotonic,
        event_history: int = 4096,
    ) -> None:
        self._bus = bus
        self._cfg = cfg = config or DriveBusConfig()
        self._ecfg = ecfg = emulator or EmulatorConfig()
        self.faults = faults or FaultInjector()
        self._clock = clock
        n = p.N_DRIVES
        self._n = n
        if dynamics is None:
            model = model or RobotModel.load()
            dynamics = RigidArm(model, ecfg.joint_damping_nms)
        self._dynamics = dynamics
        if q0 is None:
            q0 = model.q_home if model is not None else np.zeros(n)
        q = np.array(q0, dtype=np.float64)
        if q.shape != (n,) or not np.isfinite(q).all():
            raise InputError(f"q0: expected {n} finite joint positions, got {np.shape(q0)}")
        self._q = q
        self._qd = np.zeros(n)
        self._tau_max = [float(x) for x in cfg.tau_max_nm]
        first = cfg.first_node_id
        self._nodes = [first + i for i in range(n)]
        self._fb_ids = [p.FEEDBACK_BASE_ID + node for node in self._nodes]
        self._hb_ids = [p.HEARTBEAT_BASE_ID + node for node in self._nodes]
        self._emcy_ids = [p.EMCY_BASE_ID + node for node in self._nodes]

        # Per-drive state.
        self._state = [DriveState.NOT_READY_TO_SWITCH_ON] * n
        self._nmt = [NmtState.BOOT_UP] * n
        self._cw = [0] * n
        self._target = [0.0] * n
        self._limit = [0.0] * n
        self._latched = [0] * n
        self._last_fresh = [-math.inf] * n
        self._fra_time = [0.0] * n
        self._missed = [0] * n
        self._cmd: codec.CommandFrame | None = None

        t0 = clock()
        self._t0 = t0
        self._dt = cfg.cycle_period_s / ecfg.physics_substeps
        self._steps = 0  # physics steps since t0
        period = cfg.heartbeat_period_s
        # Stagger the heartbeats over one period so they do not arrive as one burst.
        self._next_hb = [t0 + period * (i + 1) / n for i in range(n)]
        self._booted = False
        self._syncs = 0

        # Modelled bus and the answers waiting for their release time.
        self._bus_free = -math.inf
        self._durations: dict[int, float] = {}
        self._pending: list[tuple[float, int, can.Message]] = []
        self._seq = 0
        self._events: deque[EmulatorEvent] = deque(maxlen=event_history)
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # ----- public API --------------------------------------------------------------------------
    @property
    def config(self) -> DriveBusConfig:
        """The bus parameters."""
        return self._cfg

    @property
    def emulator_config(self) -> EmulatorConfig:
        """The drive and arm behaviour."""
        return self._ecfg

    def step(self, now: float | None = None) -> int:
        """Process every frame pending on the bus, advance the arm, send what is due.

        Never blocks. ``now`` defaults to the clock. Returns the number of frames read.
        """
        with self._lock:
            if now is None:
                now = self._clock()
            self._begin(now)
            count = 0
            while True:
                msg = self._bus.recv(0.0)
                if msg is None:
                    break
                self._receive(msg, now)
                count += 1
            self._service(now)
            return count

    def on_message_received(self, msg: can.Message) -> None:
        """``can.Listener`` entry point (for a ``can.Notifier``; :meth:`start` is preferred,
        because a Notifier only wakes on frames and heartbeats would wait for traffic)."""
        with self._lock:
            now = self._clock()
            self._begin(now)
            self._receive(msg, now)
            self._service(now)

    def start(self) -> None:
        """Run on a named daemon thread ("drive-emulator") until :meth:`stop`."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="drive-emulator", daemon=True)
        self._thread.start()

    def stop(self, timeout: float | None = 1.0) -> None:
        """Stop the thread started by :meth:`start` (the bus stays open)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def state(self) -> EmulatorState:
        """Snapshot of the drives and the arm."""
        with self._lock:
            return EmulatorState(
                t=self._t0 + self._steps * self._dt,
                q=read_only(self._q.copy()),
                qd=read_only(self._qd.copy()),
                tau_nm=read_only(np.array([self._torque(i) for i in range(self._n)])),
                target_nm=read_only(np.array(self._target)),
                state=tuple(self._state),
                nmt=tuple(self._nmt),
                syncs=self._syncs,
                commands_missed=tuple(self._missed),
            )

    def events(self) -> list[EmulatorEvent]:
        """Everything logged so far (bounded history), oldest first."""
        with self._lock:
            return list(self._events)

    def next_due(self) -> float:
        """Clock time of the next thing the emulator will do on its own (answer, heartbeat)."""
        with self._lock:
            due = min(self._next_hb)
            if self._pending:
                due = min(due, self._pending[0][0])
            return due

    def set_arm_state(self, q: ArrayLike, qd: ArrayLike | None = None) -> None:
        """Put the arm at ``q`` (rad) with velocity ``qd`` (rad/s, default 0)."""
        qa = np.array(q, dtype=np.float64)
        qda = np.zeros(self._n) if qd is None else np.array(qd, dtype=np.float64)
        if qa.shape != (self._n,) or qda.shape != (self._n,):
            raise InputError(f"q, qd: expected shape ({self._n},)")
        with self._lock:
            self._q, self._qd = qa, qda

    # ----- thread ------------------------------------------------------------------------------
    def _run(self) -> None:
        bus = self._bus
        last = self._clock()
        while not self._stop.is_set():
            wait = min(max(self.next_due() - self._clock(), 0.0), 0.002)
            try:
                msg = bus.recv(wait)
            except can.CanError:
                break
            with self._lock:
                now = self._clock()
                if now - last > _STALL_REPORT_S:
                    # The thread waits 2 ms at most: it did not run (the machine's doing), and
                    # every answer of that time came late. Said, so that a late-feedback
                    # reaction of the loop can be told from a fault of the loop's own.
                    self._event(now, -1, "stall", f"{now - last:.6f} s")
                last = now
                self._begin(now)
                while msg is not None:
                    self._receive(msg, now)
                    msg = bus.recv(0.0)
                self._service(now)

    # ----- internals ---------------------------------------------------------------------------
    def _event(self, t: float, drive: int, kind: str, detail: str = "") -> None:
        self._events.append(EmulatorEvent(t, drive, kind, detail))

    def _duration(self, nbytes: int) -> float:
        d = self._durations.get(nbytes)
        if d is None:
            cfg = self._cfg
            d = frame_duration_s(
                nbytes, cfg.nominal_bitrate, cfg.data_bitrate, brs=cfg.bitrate_switch
            )
            self._durations[nbytes] = d
        return d

    def _occupy(self, ready: float, nbytes: int) -> float:
        """Put one frame on the modelled bus from ``ready`` on; its end time."""
        if not self._ecfg.model_bus_timing:
            return ready
        start = ready if ready > self._bus_free else self._bus_free
        end = start + self._duration(nbytes)
        self._bus_free = end
        return end

    def _tx(self, drive: int, can_id: int, data: bytes, ready: float, kind: str) -> None:
        """Queue a frame of ``drive`` for release at its modelled end of frame."""
        faults = self.faults
        if faults.is_silent(drive):
            faults.count_silent()
            return
        if faults.bus_off:
            faults.count_bus_off()
            return
        if faults.drop_tx(kind):
            return
        release = self._occupy(ready, len(data)) + faults.delay()
        msg = can.Message(
            timestamp=release,
            arbitration_id=can_id,
            is_extended_id=False,
            is_fd=True,
            bitrate_switch=self._cfg.bitrate_switch,
            data=data,
            check=False,
        )
        heapq.heappush(self._pending, (release, self._seq, msg))
        self._seq += 1

    def _flush(self, now: float) -> None:
        pending = self._pending
        while pending and pending[0][0] <= now + 1e-12:
            _, _, msg = heapq.heappop(pending)
            try:
                self._bus.send(msg)
            except can.CanError:
                self.faults.count_bus_off()

    def _torque(self, i: int) -> float:
        state = self._state[i]
        if state is DriveState.OPERATION_ENABLED:
            lim = min(self._limit[i], self._tau_max[i])
            t = self._target[i]
            return lim if t > lim else -lim if t < -lim else t
        if state is DriveState.QUICK_STOP_ACTIVE:
            lim = self._tau_max[i]
            t = -self._ecfg.quick_stop_damping_nms * float(self._qd[i])
            return lim if t > lim else -lim if t < -lim else t
        return 0.0

    def _begin(self, now: float) -> None:
        """Boot on the first call, then bring the arm up to ``now``; before any frame is read."""
        if not self._booted:
            self._booted = True
            for i in range(self._n):
                self._set_state(i, DriveState.SWITCH_ON_DISABLED, now)  # transitions 0, 1
                boot = codec.encode_heartbeat(NmtState.BOOT_UP)
                self._tx(i, self._hb_ids[i], boot, now, "heartbeat")
                start = NmtState.OPERATIONAL if self._ecfg.auto_start else NmtState.PRE_OPERATIONAL
                self._set_nmt(i, start, now)
        self._advance(now)

    def _advance(self, t: float) -> None:
        """Integrate the arm on its fixed grid up to ``t``."""
        dt = self._dt
        target_steps = math.floor((t - self._t0) / dt + 1e-9)
        if target_steps <= self._steps:
            return
        skip = target_steps - self._steps - math.ceil(self._ecfg.max_catch_up_s / dt)
        if skip > 0:
            self._steps += skip
            self._event(t, -1, "physics_skip", f"{skip * dt:.6f} s")
        brake = self._ecfg.brake_when_disabled
        n = self._n
        while self._steps < target_steps:
            active = [self._state[i] in _ENABLED_OR_BRAKING for i in range(n)]
            if brake and not any(active):
                # Every joint held: nothing moves; skip the dynamics.
                self._qd[:] = 0.0
                self._steps = target_steps
                break
            tau = np.array([self._torque(i) for i in range(n)])
            q_next, qd_next = self._dynamics(self._q, self._qd, tau, dt)
            q_next = np.array(q_next, dtype=np.float64)
            qd_next = np.array(qd_next, dtype=np.float64)
            if brake:
                for i in range(n):
                    if not active[i]:
                        q_next[i] = self._q[i]
                        qd_next[i] = 0.0
            self._q, self._qd = q_next, qd_next
            self._steps += 1

    def _set_state(self, i: int, state: DriveState, t: float) -> None:
        if state is not self._state[i]:
            self._state[i] = state
            self._event(t, i, "state", state.name)

    def _fault(self, i: int, code: int, t: float) -> None:
        self._set_state(i, DriveState.FAULT_REACTION_ACTIVE, t)
        self._fra_time[i] = t
        self._event(t, i, "fault", f"0x{code:04X}")
        self._emcy(i, code, t)

    def _emcy(self, i: int, code: int, t: float) -> None:
        data = codec.encode_emcy(code, p.error_register_for(code), self._nodes[i], self._latched[i])
        self._tx(i, self._emcy_ids[i], data, t, "emcy")

    def _set_nmt(self, i: int, state: NmtState, t: float) -> None:
        if state is not self._nmt[i]:
            self._nmt[i] = state
            self._event(t, i, "nmt", state.name)

    def _receive(self, msg: can.Message, now: float) -> None:
        if msg.is_error_frame:
            return
        can_id = msg.arbitration_id
        if can_id == p.COMMAND_ID:
            kind = "command"
        elif can_id == p.SYNC_ID:
            kind = "sync"
        elif can_id == p.NMT_ID:
            kind = "nmt"
        else:
            return  # another node's frame
        faults = self.faults
        if faults.bus_off:
            faults.count_bus_off()
            return
        if faults.drop_rx(kind):
            return
        end = self._occupy(now, len(msg.data))
        if kind == "command":
            try:
                self._cmd = codec.decode_command(msg.data)
            except struct.error:
                return
        elif kind == "sync":
            self._on_sync(msg.data[0] if msg.data else 0, end)
        else:
            self._on_nmt(msg.data, end)

    def _on_nmt(self, data: bytes | bytearray, t: float) -> None:
        if len(data) < 2:
            return
        try:
            command = NmtCommand(data[0])
        except ValueError:
            return
        for i in range(self._n):
            if data[1] not in (0, self._nodes[i]):
                continue
            if self.faults.is_silent(i):
                self.faults.count_silent()
                continue
            if command is NmtCommand.START:
                self._set_nmt(i, NmtState.OPERATIONAL, t)
            elif command is NmtCommand.STOP:
                self._set_nmt(i, NmtState.STOPPED, t)
            elif command is NmtCommand.ENTER_PRE_OPERATIONAL:
                self._set_nmt(i, NmtState.PRE_OPERATIONAL, t)
            else:  # reset node / communication: reboot
                self._set_state(i, DriveState.SWITCH_ON_DISABLED, t)
                self._set_nmt(i, NmtState.PRE_OPERATIONAL, t)
                boot = codec.encode_heartbeat(NmtState.BOOT_UP)
                self._tx(i, self._hb_ids[i], boot, t, "heartbeat")

    def _on_sync(self, counter: int, t: float) -> None:
        self._syncs += 1
        cmd = self._cmd
        # A command is latched once: a second SYNC without a new frame finds nothing fresh.
        fresh = cmd is not None and (cmd.cycle & 0xFF) == counter
        self._cmd = None
        ready = t + self._ecfg.drive_response_s
        timeout = self._ecfg.command_timeout_s
        faults = self.faults
        for i in range(self._n):
            if self._nmt[i] is not NmtState.OPERATIONAL:
                continue
            if faults.is_silent(i):
                faults.count_silent()
                continue
            prev_cw = self._cw[i]
            if fresh:
                assert cmd is not None
                self._cw[i] = cmd.controlword[i]
                self._target[i] = cmd.torque_nm[i]
                self._limit[i] = cmd.torque_limit_nm[i]
                self._latched[i] = cmd.cycle
                self._last_fresh[i] = t
            else:
                self._missed[i] += 1
            state = self._state[i]
            if state not in _FAULTY and (code := faults.take_drive_fault(i)):
                self._fault(i, code, t)
            elif state is DriveState.FAULT_REACTION_ACTIVE:
                if t > self._fra_time[i]:
                    self._set_state(i, DriveState.FAULT, t)
            else:
                new = p.next_state(state, self._cw[i], prev_cw)
                if state is DriveState.FAULT and faults.fault_active(i):
                    new = state  # the cause persists: the reset is refused
                if new is not state:
                    self._set_state(i, new, t)
                    if state is DriveState.FAULT:
                        self._emcy(i, EmcyCode.NO_ERROR, t)
            if self._state[i] in _ENABLED_OR_BRAKING and t - self._last_fresh[i] > timeout:
                self._event(t, i, "command_timeout")
                self._fault(i, EmcyCode.COMMAND_TIMEOUT, t)
            data = codec.encode_feedback(
                float(self._q[i]),
                float(self._qd[i]),
                self._torque(i),
                p.statusword_of(self._state[i]),
                counter,
                self._latched[i],
            )
            self._tx(i, self._fb_ids[i], data, ready, "feedback")

    def _service(self, now: float) -> None:
        self._begin(now)
        faults = self.faults
        n = self._n
        timeout = self._ecfg.command_timeout_s
        period = self._cfg.cycle_period_s
        for i in range(n):
            state = self._state[i]
            operational = self._nmt[i] is NmtState.OPERATIONAL
            if state not in _FAULTY and operational and (code := faults.take_drive_fault(i)):
                self._fault(i, code, now)
                continue
            if state is DriveState.FAULT_REACTION_ACTIVE and now - self._fra_time[i] >= period:
                self._set_state(i, DriveState.FAULT, now)
            elif state in _ENABLED_OR_BRAKING and now - self._last_fresh[i] > timeout:
                self._event(now, i, "command_timeout")
                self._fault(i, EmcyCode.COMMAND_TIMEOUT, now)
        hb_period = self._cfg.heartbeat_period_s
        for i in range(n):
            due = self._next_hb[i]
            if due > now:
                continue
            if now - due > 2 * hb_period:
                due = now  # fell behind (thread paused): resynchronise instead of bursting
            if not faults.heartbeat_suppressed(i):
                self._tx(i, self._hb_ids[i], codec.encode_heartbeat(self._nmt[i]), due, "heartbeat")
            self._next_hb[i] = due + hb_period
        self._flush(now)
