"""The master side of the drive bus: command + SYNC out, feedback, heartbeats and EMCY in.

:class:`DriveLink` takes an open python-can bus (``can.BusABC``; it never creates one) and is
driven by the control loop, once per cycle::

    fb = link.poll_feedback()                 # answers to the previous SYNC (non-blocking)
    tau = controller(fb)                      # N m
    link.send_command(tau, link.controlwords(DriveTarget.ENABLED))
    link.send_sync()

Everything the loop or an observer needs is in the immutable :class:`DriveFeedback` it returns
(arrays are read-only; each snapshot has a sequence number). The link is the last line of
defence for torque: every command is clamped to the configured per-drive limit, a non-finite
torque becomes 0, and a drive gets a non-zero torque only when its latest feedback is fresh and
says OPERATION ENABLED and this command keeps it enabled. Nothing on the hot path raises: failed
sends are counted and, after ``send_errors_for_bus_off`` in a row, reported as bus-off.

The link is not thread-safe: one thread (the control loop) drives it; others read its snapshots.
Time comes from ``clock`` (``time.monotonic`` unless a test passes a fake one), so heartbeat and
feedback timeouts are decided from recorded times, never by sleeping.
"""

from __future__ import annotations

import math
import struct
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import can
import numpy as np
from hapticloud.core.errors import ConfigError, DriveError, InputError
from hapticloud.core.validation import read_only
from numpy.typing import ArrayLike, NDArray

from . import codec
from . import protocol as p
from .config import DriveBusConfig
from .faults import CAN_ERR_BUSOFF, CAN_ERR_RESTARTED
from .protocol import DriveState, DriveTarget, NmtState
from .schedule import frame_duration_s

FloatArray = NDArray[np.float64]
Clock = Callable[[], float]

_FEEDBACK, _HEARTBEAT, _EMCY = 1, 2, 3
_MAX_FRAMES_PER_POLL = 512
_ENABLE_MASK = 0x8F
_FAULT_BIT = int(p.Statusword.FAULT)  # bits that make up the "enable operation" command
#: Torque counts at or beyond this are clamped without rounding: a torque above ~9e305 N m has an
#: infinite count, and ``round(inf)`` raises. Any limit in counts (int16) is far below it.
_SATURATED_COUNT = float(1 << 20)


class LinkCounters(NamedTuple):
    """Running totals of the link (since construction)."""

    commands_sent: int
    syncs_sent: int
    feedback_received: int
    #: Feedback frames that had not arrived when the next SYNC was sent.
    feedback_missing: int
    #: Feedback frames that arrived after the next SYNC (also counted as missing).
    feedback_late: int
    #: Feedback frames in which a drive said it had not received that cycle's command.
    commands_missed: int
    heartbeats: int
    emergencies: int
    error_frames: int
    send_errors: int
    #: Exceptions raised by ``bus.recv`` (a backend's way of reporting a controller error).
    receive_errors: int
    bus_off_events: int
    unknown_frames: int
    #: Torque commands cut to the drive limit.
    torques_clamped: int
    #: Non-finite torque commands replaced by 0.
    torques_nonfinite: int
    #: Non-zero torque commands replaced by 0 because the drive was not (known to be) enabled.
    torques_blocked: int
    #: Wire time of every frame sent or received (s, modelled at the configured bit rates):
    #: its change over the change of :attr:`DriveFeedback.stamp` is the observed bus load.
    bus_time_s: float


class LinkEvent(NamedTuple):
    """Something the link noticed: ``kind`` is one of ``"state"`` (a drive's CiA 402 state
    changed; ``detail`` is the new :class:`DriveState` name), ``"emcy"`` (``detail``
    ``"0x2310"``), ``"heartbeat_lost"``, ``"heartbeat_back"``, ``"reboot"`` (boot-up heartbeat),
    ``"bus_off"``, ``"bus_back"``. ``drive`` is -1 for bus events; ``stamp`` is link clock time."""

    stamp: float
    drive: int
    kind: str
    detail: str


class Emergency(NamedTuple):
    """A received EMCY: drive index, error ``code``, error ``register``, the command ``cycle``
    (low 32 bits) the drive had latched, and the link clock time it was received."""

    stamp: float
    drive: int
    code: int
    register: int
    cycle: int


def _array(name: str, dtype: Any = np.float64) -> Any:
    """A read-only array attribute of :class:`DriveFeedback` built from its raw tuple when first
    read: the control loop reads a few of them per tick, observers the rest."""

    def get(self: DriveFeedback) -> NDArray:
        cache = self._cache
        arr = cache.get(name)
        if arr is None:
            arr = cache[name] = read_only(np.array(self._raw[name], dtype=dtype))
        return arr

    get.__name__ = name
    return property(get)


class DriveFeedback:
    """Immutable snapshot of the six drives, returned by :meth:`DriveLink.poll_feedback`.

    Arrays have shape (6,) in drive order and are read-only. ``cycle`` is the command cycle of
    the latest SYNC sent; ``fresh[i]`` says drive ``i``'s feedback for that SYNC has arrived
    (the values are otherwise those of its newest frame, ``age_s[i]`` old).

    Attributes
    ----------
    seq
        Snapshot sequence number (increments per snapshot).
    stamp
        Link clock time of the snapshot (s).
    position_rad, velocity_rad_s, torque_nm, statusword, state, fresh
        Per drive, from its newest feedback frame.
    age_s
        Time since the SYNC at which each drive's newest feedback was sampled (s; one cycle in
        steady state, since the loop reads the answers to the previous SYNC); inf if none yet.
    stale
        Feedback older than ``feedback_timeout_s`` (or none at all).
    command_missed
        The drive's newest feedback says it did not get that cycle's command (it held the last).
    heartbeat_age_s
        Time since each drive's newest heartbeat (s); inf if none yet.
    heartbeat_lost
        No heartbeat for longer than ``heartbeat_timeout_s`` (counted from link start if none).
    error_code
        Latest EMCY error code per drive (0: none, or reset).
    oldest_age_s, any_stale, any_heartbeat_lost, any_fault_bit, oldest_heartbeat_age_s
        Summaries for the control loop, computed from the link's lists: the largest ``age_s``,
        whether any drive is ``stale``, has lost its heartbeat or has the fault bit set, and the
        largest ``heartbeat_age_s`` (a never-heard drive counting as old as the link).

    The arrays other than position and velocity are built from raw tuples when first read.
    """

    __slots__ = (
        "_cache",
        "_counters",
        "_raw",
        "any_fault_bit",
        "any_heartbeat_lost",
        "any_stale",
        "bus_off",
        "cycle",
        "nmt_state",
        "oldest_age_s",
        "oldest_heartbeat_age_s",
        "position_rad",
        "seq",
        "stamp",
        "state",
        "velocity_rad_s",
    )

    seq: int
    stamp: float
    cycle: int
    position_rad: FloatArray
    velocity_rad_s: FloatArray
    state: tuple[DriveState, ...]
    nmt_state: tuple[NmtState | None, ...]
    bus_off: bool
    oldest_age_s: float
    any_stale: bool
    any_heartbeat_lost: bool
    any_fault_bit: bool
    oldest_heartbeat_age_s: float

    def __init__(
        self,
        *,
        seq: int,
        stamp: float,
        cycle: int,
        position_rad: Sequence[float],
        velocity_rad_s: Sequence[float],
        state: tuple[DriveState, ...],
        nmt_state: tuple[NmtState | None, ...],
        bus_off: bool,
        counters: dict[str, Any],
        raw: dict[str, tuple[Any, ...]],
        oldest_age_s: float,
        any_stale: bool,
        any_heartbeat_lost: bool,
        any_fault_bit: bool,
        oldest_heartbeat_age_s: float,
    ) -> None:
        init = object.__setattr__
        init(self, "seq", seq)
        init(self, "stamp", stamp)
        init(self, "cycle", cycle)
        init(self, "position_rad", read_only(np.array(position_rad)))
        init(self, "velocity_rad_s", read_only(np.array(velocity_rad_s)))
        init(self, "state", state)
        init(self, "nmt_state", nmt_state)
        init(self, "bus_off", bus_off)
        init(self, "_counters", counters)
        init(self, "_raw", raw)
        init(self, "_cache", {})
        init(self, "oldest_age_s", oldest_age_s)
        init(self, "any_stale", any_stale)
        init(self, "any_heartbeat_lost", any_heartbeat_lost)
        init(self, "any_fault_bit", any_fault_bit)
        init(self, "oldest_heartbeat_age_s", oldest_heartbeat_age_s)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"DriveFeedback is immutable (cannot set {name!r})")

    def __getstate__(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in self.__slots__ if name != "_cache"}

    def __setstate__(self, state: dict[str, Any]) -> None:
        for name, value in state.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, "_cache", {})

    def __repr__(self) -> str:
        return (
            f"DriveFeedback(seq={self.seq}, stamp={self.stamp:.6f}, cycle={self.cycle}, "
            f"complete={self.complete}, any_fault={self.any_fault_bit}, bus_off={self.bus_off})"
        )

    torque_nm = _array("torque_nm")
    statusword = _array("statusword", np.uint16)
    fresh = _array("fresh", np.bool_)
    age_s = _array("age_s")
    stale = _array("stale", np.bool_)
    command_missed = _array("command_missed", np.bool_)
    heartbeat_age_s = _array("heartbeat_age_s")
    heartbeat_lost = _array("heartbeat_lost", np.bool_)
    error_code = _array("error_code", np.uint16)
    torque_limit_nm = _array("torque_limit_nm")

    @property
    def counters(self) -> LinkCounters:
        """The link's running totals at this snapshot."""
        return LinkCounters(**self._counters)

    def bus_load_since(self, earlier: DriveFeedback) -> float:
        """Observed bus load between ``earlier`` and this snapshot (fraction of the time the
        frames this link sent and received occupied the bus; other nodes' frames and lost ones
        are not seen). Compare with :func:`.schedule.config_load`, the planned figure."""
        dt = self.stamp - earlier.stamp
        if not dt > 0.0:
            return 0.0
        return (self._counters["bus_time_s"] - earlier._counters["bus_time_s"]) / dt

    @property
    def missing(self) -> tuple[int, ...]:
        """Drives whose feedback for the latest SYNC has not arrived."""
        return tuple(int(i) for i in np.flatnonzero(~self.fresh))

    @property
    def complete(self) -> bool:
        """All six drives answered the latest SYNC."""
        return all(self._raw["fresh"])

    @property
    def faulted(self) -> NDArray[np.bool_]:
        """Statusword fault bit per drive (FAULT or FAULT REACTION ACTIVE)."""
        return read_only((self.statusword & p.Statusword.FAULT) != 0)

    @property
    def any_fault(self) -> bool:
        """Any drive reports a fault."""
        return bool(self.faulted.any())

    @property
    def enabled(self) -> NDArray[np.bool_]:
        """Drives in OPERATION ENABLED with fresh enough feedback."""
        ok = np.array([s is DriveState.OPERATION_ENABLED for s in self.state])
        return read_only(ok & ~self.stale)

    @property
    def all_enabled(self) -> bool:
        """All drives in OPERATION ENABLED with fresh enough feedback."""
        return bool(self.enabled.all())


class DriveLink:
    """Master side of the CiA 402-style CST profile on a CAN FD bus.

    Parameters
    ----------
    bus
        An open CAN FD bus (``can.Bus(..., fd=True)``; for the ``virtual`` interface pass
        ``protocol=can.CanProtocol.CAN_FD``). The link does not shut it down.
    config
        Bus parameters (rates, node ids, torque limits, timeouts).
    clock
        Time source in seconds; ``time.monotonic`` by default. Deadlines given to
        :meth:`poll_feedback` are in this clock.
    send_timeout_s
        Timeout passed to ``bus.send``; 0 never blocks the loop on a full transmit queue.

    Raises
    ------
    ConfigError
        If the bus is a classic CAN 2.0 bus (the 48-byte command frame needs CAN FD).
    """

    def __init__(
        self,
        bus: can.BusABC,
        config: DriveBusConfig | None = None,
        *,
        clock: Clock = time.monotonic,
        send_timeout_s: float | None = 0.0,
        event_history: int = 1024,
    ) -> None:
        if getattr(bus, "protocol", None) == can.CanProtocol.CAN_20:
            raise ConfigError(
                "bus: speaks classic CAN 2.0; the drive protocol needs CAN FD (open it with "
                "fd=True; for the virtual interface protocol=can.CanProtocol.CAN_FD)"
            )
        self._bus = bus
        # A bus with the raw fast path (:class:`~.transport.SocketPairBus`) skips building a
        # ``can.Message`` per frame: most of the master's per-frame cost in the tick.
        self._send_frame = getattr(bus, "send_frame", None)
        self._send_frames = getattr(bus, "send_frames", None)
        self._read_frames = getattr(bus, "read_frames", None)
        self._cfg = cfg = config or DriveBusConfig()
        self._clock = clock
        self._send_timeout = send_timeout_s
        n = p.N_DRIVES
        self._n = n
        first = cfg.first_node_id
        self._dispatch: dict[int, tuple[int, int]] = {}
        for i in range(n):
            self._dispatch[p.FEEDBACK_BASE_ID + first + i] = (_FEEDBACK, i)
            self._dispatch[p.HEARTBEAT_BASE_ID + first + i] = (_HEARTBEAT, i)
            self._dispatch[p.EMCY_BASE_ID + first + i] = (_EMCY, i)
        self._tau_max = [float(x) for x in cfg.tau_max_nm]
        self._limit = list(self._tau_max)
        self._limit_raw = [self._raw_limit(x) for x in self._limit]

        # Latest per-drive values (Python lists: scalar writes per frame are cheaper than numpy).
        self._pos = [0.0] * n
        self._vel = [0.0] * n
        self._tau = [0.0] * n
        self._sw = [0] * n
        self._state = [DriveState.NOT_READY_TO_SWITCH_ON] * n
        self._cmd_missed = [False] * n
        # Link clock time of the SYNC each drive's newest feedback was sampled at; a late frame
        # therefore looks as old as its data is, not as fresh as its arrival.
        self._sample_time = [-math.inf] * n
        self._sync_time = [-math.inf] * 256  # send time of the SYNC with each counter value
        self._fresh = [False] * n
        self._n_fresh = 0
        self._nmt: list[NmtState | None] = [None] * n
        self._hb_time = [-math.inf] * n
        self._hb_lost = [False] * n
        self._err = [0] * n
        self._cw_sent = [0] * n
        self._cw_cache: dict[tuple[Any, ...], tuple[int, ...]] = {}

        self._cycle = 0  # cycle of the latest command sent
        self._command_pending = False  # a command was sent since the last SYNC
        self._next_cycle = 0
        self._sync_cycle = -1  # cycle of the latest SYNC sent (-1: none yet)
        self._sync_counter = -1
        self._bus_off = False
        self._consecutive_send_errors = 0
        self._start = clock()
        self._seq = 0
        self._events: deque[LinkEvent] = deque(maxlen=event_history)
        self._emcy: deque[Emergency] = deque(maxlen=event_history)
        self._c: dict[str, Any] = dict.fromkeys(LinkCounters._fields, 0)
        self._c["bus_time_s"] = 0.0
        self._durations = {
            n: frame_duration_s(n, cfg.nominal_bitrate, cfg.data_bitrate, brs=cfg.bitrate_switch)
            for n in (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
        }

    # ----- properties --------------------------------------------------------------------------
    @property
    def config(self) -> DriveBusConfig:
        """The bus parameters."""
        return self._cfg

    @property
    def bus(self) -> can.BusABC:
        """The bus the link talks on."""
        return self._bus

    @property
    def n_drives(self) -> int:
        """Number of drives (6)."""
        return self._n

    @property
    def cycle(self) -> int:
        """Cycle counter of the latest command sent."""
        return self._cycle

    @property
    def torque_limits(self) -> FloatArray:
        """Torque limits in force (N m): the configured ones, or lower ones set at run time."""
        return read_only(np.array(self._limit))

    @property
    def counters(self) -> LinkCounters:
        """Running totals."""
        return LinkCounters(**self._c)

    # ----- helpers -----------------------------------------------------------------------------
    @staticmethod
    def _raw_limit(limit_nm: float) -> int:
        # Rounded down, so that a quantised torque never exceeds the limit in N m.
        return min(p.INT16_MAX, math.floor(limit_nm / p.TORQUE_LSB_NM + 1e-9))

    def _event(self, drive: int, kind: str, detail: str = "") -> None:
        self._events.append(LinkEvent(self._clock(), drive, kind, detail))

    def _message(self, can_id: int, data: bytes) -> can.Message:
        return can.Message(
            arbitration_id=can_id,
            is_extended_id=False,
            is_fd=True,
            bitrate_switch=self._cfg.bitrate_switch,
            data=data,
            check=False,
        )

    def _send_data(self, can_id: int, data: bytes) -> bool:
        if self._send_frame is None:
            return self._send(self._message(can_id, data))
        try:
            self._send_frame(can_id, data, True, self._cfg.bitrate_switch)
        except can.CanError:
            return self._send_failed()
        return self._sent(len(data))

    def _send_all(self, frames: tuple[tuple[int, bytes], ...]) -> list[bool]:
        """Send data frames in order: one burst where the bus takes bursts (all or none sent),
        else one by one. Whether each was sent; send errors and bus time counted per frame."""
        if self._send_frames is None:
            return [self._send_data(can_id, data) for can_id, data in frames]
        try:
            self._send_frames(frames, True, self._cfg.bitrate_switch)
        except can.CanError:
            return [self._send_failed() for _ in frames]
        return [self._sent(len(data)) for _, data in frames]

    def _send_failed(self) -> bool:
        self._c["send_errors"] += 1
        self._consecutive_send_errors += 1
        if self._consecutive_send_errors >= self._cfg.send_errors_for_bus_off and not self._bus_off:
            self._set_bus_off(True)
        return False

    def _sent(self, nbytes: int) -> bool:
        self._consecutive_send_errors = 0
        self._c["bus_time_s"] += self._durations.get(nbytes, 0.0)
        if self._bus_off:
            self._set_bus_off(False)
        return True

    def _send(self, msg: can.Message) -> bool:
        try:
            self._bus.send(msg, self._send_timeout)
        except can.CanError:
            return self._send_failed()
        return self._sent(len(msg.data))

    def _set_bus_off(self, off: bool) -> None:
        if off and not self._bus_off:
            self._c["bus_off_events"] += 1
            self._event(-1, "bus_off")
        elif not off and self._bus_off:
            self._event(-1, "bus_back")
        self._bus_off = off

    # ----- commands ----------------------------------------------------------------------------
    def set_torque_limits(self, limits_nm: ArrayLike) -> None:
        """Lower the per-drive torque limits (N m) at run time (e.g. while ramping up or in a
        damped safe state). Values above the configured limits are cut to them; sent to the
        drives in every command (they clamp to it too)."""
        arr = np.asarray(limits_nm, dtype=np.float64)
        if arr.shape == ():
            arr = np.full(self._n, float(arr))
        if arr.shape != (self._n,) or not np.all(arr >= 0.0):
            raise InputError(f"limits_nm: expected {self._n} numbers >= 0, got {arr.tolist()}")
        self._limit = [min(float(a), m) for a, m in zip(arr, self._tau_max, strict=True)]
        self._limit_raw = [self._raw_limit(x) for x in self._limit]

    def controlwords(self, target: DriveTarget | Sequence[DriveTarget]) -> tuple[int, ...]:
        """Controlwords that move every drive one CiA 402 step towards ``target`` (one target for
        all drives or one per drive), from the states of the latest feedback."""
        targets = (target,) * self._n if isinstance(target, DriveTarget) else tuple(target)
        if len(targets) != self._n:
            raise InputError(f"target: expected 1 or {self._n} targets, got {len(targets)}")
        # The words depend only on (targets, states, last words): in steady state the same key
        # every tick, so the answer is looked up instead of recomputed.
        key = (targets, tuple(self._state), tuple(self._cw_sent))
        words = self._cw_cache.get(key)
        if words is None:
            words = tuple(
                p.controlword_towards(self._state[i], targets[i], self._cw_sent[i])
                for i in range(self._n)
            )
            if len(self._cw_cache) >= 256:
                self._cw_cache.clear()
            self._cw_cache[key] = words
        return words

    def send_command(
        self,
        torques: ArrayLike,
        controlwords: Sequence[int],
        cycle: int | None = None,
    ) -> FloatArray:
        """Send the command frame: target torques and controlwords of all six drives.

        Parameters
        ----------
        torques
            Six target torques (N m). Clamped to the torque limits; non-finite values become 0;
            a drive that is not enabled (latest fresh feedback OPERATION ENABLED, and this
            controlword "enable operation") gets 0.
        controlwords
            Six CiA 402 controlwords (see :meth:`controlwords`).
        cycle
            Cycle counter; by default one more than the previous command's.

        Returns
        -------
        numpy.ndarray
            The torques actually sent (N m, after clamping and quantisation), shape (6,).
        """
        data, sent = self._command_frame(torques, controlwords, cycle)
        if self._send_data(p.COMMAND_ID, data):
            self._c["commands_sent"] += 1
        return sent

    def send_cycle(self, torques: ArrayLike, controlwords: Sequence[int]) -> FloatArray:
        """:meth:`send_command`, then :meth:`send_sync`: one cycle's frames, in one burst where
        the bus takes bursts (:meth:`~.transport.SocketPairBus.send_frames`: one system call and
        one wake-up of the drives instead of two). Same frames, order, counters and return."""
        command, sent = self._command_frame(torques, controlwords, None)
        command_ok, sync_ok = self._send_all(
            ((p.COMMAND_ID, command), (p.SYNC_ID, self._sync_frame()))
        )
        if command_ok:
            self._c["commands_sent"] += 1
        if sync_ok:
            self._c["syncs_sent"] += 1
        return sent

    def _command_frame(
        self, torques: ArrayLike, controlwords: Sequence[int], cycle: int | None
    ) -> tuple[bytes, FloatArray]:
        """The command frame's data and the torques it carries (N m); the cycle is taken."""
        tau = np.asarray(torques, dtype=np.float64)
        if tau.shape != (self._n,):
            raise InputError(f"torques: expected shape ({self._n},), got {np.shape(torques)}")
        if len(controlwords) != self._n:
            raise InputError(f"controlwords: expected {self._n} words, got {len(controlwords)}")
        cws = [int(c) for c in controlwords]
        for c in cws:
            if not 0 <= c <= 0xFFFF:
                raise InputError(f"controlwords: {c} is not a 16-bit word")
        if cycle is None:
            cycle = self._next_cycle
        cycle &= 0xFFFFFFFF
        now = self._clock()
        timeout = self._cfg.feedback_timeout_s
        raw = [0] * self._n
        c = self._c
        for i, t in enumerate(tau.tolist()):
            if t != t or t in (math.inf, -math.inf):
                c["torques_nonfinite"] += 1
                continue
            enabled = (
                self._state[i] is DriveState.OPERATION_ENABLED
                and (cws[i] & _ENABLE_MASK) == p.CW_ENABLE_OPERATION
                and now - self._sample_time[i] <= timeout
            )
            if not enabled:
                if t != 0.0:
                    c["torques_blocked"] += 1
                continue
            lim = self._limit_raw[i]
            x = t / p.TORQUE_LSB_NM
            if -_SATURATED_COUNT < x < _SATURATED_COUNT:
                r = round(x)
            else:  # clamped just below
                r = lim + 1 if x > 0.0 else -lim - 1
            if r > lim:
                r = lim
                c["torques_clamped"] += 1
            elif r < -lim:
                r = -lim
                c["torques_clamped"] += 1
            raw[i] = r
        limits = [max(0, x) for x in self._limit_raw]
        data = codec.encode_command_raw(cycle, cws, raw, limits)
        self._cycle = cycle
        self._next_cycle = (cycle + 1) & 0xFFFFFFFF
        self._cw_sent = cws
        self._command_pending = True
        return data, np.array(raw, dtype=np.float64) * p.TORQUE_LSB_NM

    def send_sync(self) -> bool:
        """Send SYNC for the latest command's cycle; the drives latch it and answer.

        Closes the previous cycle: drives that have not answered its SYNC are counted missing.
        A SYNC without a command since the previous one gets the next cycle number, so the drives
        hold their last command and flag it. Returns whether the frame was sent.
        """
        sent = self._send_data(p.SYNC_ID, self._sync_frame())
        if sent:
            self._c["syncs_sent"] += 1
        return sent

    def _sync_frame(self) -> bytes:
        """The SYNC frame's data; the previous cycle is closed and this one's time taken."""
        if not self._command_pending:
            # No command since the last SYNC: advance the counter anyway, so that the drives see
            # that they got no fresh command (and report it) instead of re-latching the old one.
            self._cycle = self._next_cycle
            self._next_cycle = (self._cycle + 1) & 0xFFFFFFFF
        self._command_pending = False
        if self._sync_cycle >= 0:
            self._c["feedback_missing"] += self._n - self._n_fresh
        self._fresh = [False] * self._n
        self._n_fresh = 0
        self._sync_cycle = self._cycle
        self._sync_counter = self._cycle & 0xFF
        self._sync_time[self._sync_counter] = self._clock()
        return codec.encode_sync(self._sync_counter)

    def send_nmt(self, command: p.NmtCommand, drive: int | None = None) -> bool:
        """Send an NMT command to ``drive`` (index) or to all drives."""
        node = 0 if drive is None else self._cfg.first_node_id + drive
        return self._send_data(p.NMT_ID, codec.encode_nmt(command, node))

    def start_nodes(self) -> bool:
        """NMT start for all drives (PRE-OPERATIONAL -> OPERATIONAL)."""
        return self.send_nmt(p.NmtCommand.START)

    # ----- receiving ---------------------------------------------------------------------------
    def handle(self, msg: can.Message) -> None:
        """Process one received frame (also usable to decode a recorded log offline)."""
        self._handle(msg.arbitration_id, msg.data, msg.is_error_frame)

    def _handle(self, can_id: int, data: bytes | bytearray, is_error: bool) -> None:
        if is_error:
            self._c["error_frames"] += 1
            if can_id & CAN_ERR_BUSOFF:
                self._set_bus_off(True)
            elif can_id & CAN_ERR_RESTARTED:
                self._set_bus_off(False)
            return
        self._c["bus_time_s"] += self._durations.get(len(data), 0.0)
        entry = self._dispatch.get(can_id)
        if entry is None:
            self._c["unknown_frames"] += 1
            return
        kind, i = entry
        now = self._clock()
        if kind == _FEEDBACK:
            try:
                pos, vel, tau, sw, sync, cmd = codec.FEEDBACK.unpack_from(data)
            except struct.error:  # a short frame is a bus error, not a crash
                self._c["unknown_frames"] += 1
                return
            self._c["feedback_received"] += 1
            if sync == self._sync_counter:
                if self._fresh[i]:
                    return  # duplicate
                self._fresh[i] = True
                self._n_fresh += 1
            else:
                self._c["feedback_late"] += 1
            self._pos[i] = pos * p.POSITION_LSB_RAD
            self._vel[i] = vel * p.VELOCITY_LSB_RAD_S
            self._tau[i] = tau * p.TORQUE_LSB_NM
            sampled = self._sync_time[sync]
            # A frame answering a SYNC this link did not send (a recorded log): received now.
            self._sample_time[i] = sampled if sampled > -math.inf else now
            missed = cmd != sync
            self._cmd_missed[i] = missed
            if missed:
                self._c["commands_missed"] += 1
            if sw != self._sw[i]:
                self._sw[i] = sw
                state = p.state_of(sw)
                if state is not self._state[i]:
                    self._state[i] = state
                    self._event(i, "state", state.name)
        elif kind == _HEARTBEAT:
            if not data:
                self._c["unknown_frames"] += 1
                return
            self._c["heartbeats"] += 1
            try:
                state = NmtState(data[0])
            except ValueError:
                self._c["unknown_frames"] += 1
                return
            if state is NmtState.BOOT_UP and self._nmt[i] is not None:
                self._event(i, "reboot")
            self._nmt[i] = state
            self._hb_time[i] = now
        else:
            try:
                e = codec.decode_emcy(data)
            except struct.error:
                self._c["unknown_frames"] += 1
                return
            self._c["emergencies"] += 1
            self._err[i] = e.code
            self._emcy.append(Emergency(now, i, e.code, e.register, e.cycle))
            self._event(i, "emcy", f"0x{e.code:04X}")

    def read_pending(self) -> int:
        """Handle every frame received so far, without waiting and without a snapshot (the
        control loop calls it just before its deadline, so that the tick finds little left to
        decode). Returns the number of frames handled."""
        n = 0
        try:
            if self._read_frames is not None:
                handle = self._handle
                for can_id, data, is_error in self._read_frames(_MAX_FRAMES_PER_POLL):
                    handle(can_id, data, is_error)
                    n += 1
                return n
            recv = self._bus.recv
            for _ in range(_MAX_FRAMES_PER_POLL):
                msg = recv(0.0)
                if msg is None:
                    break
                self.handle(msg)
                n += 1
        except can.CanError:
            # Some backends raise from recv on a controller error; the loop must go on.
            self._c["receive_errors"] += 1
        return n

    def poll_feedback(self, deadline: float | None = None) -> DriveFeedback:
        """Collect received frames and return a snapshot.

        Parameters
        ----------
        deadline
            ``None``: take only what has arrived (never blocks). Otherwise wait, until this time
            of the link clock at the latest, for all six answers to the latest SYNC.
        """
        if deadline is None:
            self.read_pending()
            return self.snapshot()
        bus = self._bus
        try:
            for _ in range(_MAX_FRAMES_PER_POLL):
                msg = bus.recv(0.0)
                if msg is None:
                    if self._n_fresh == self._n:
                        break
                    remaining = deadline - self._clock()
                    if remaining <= 0.0:
                        break
                    msg = bus.recv(remaining)
                    if msg is None:
                        break
                self.handle(msg)
        except can.CanError:
            self._c["receive_errors"] += 1
        return self.snapshot()

    def snapshot(self) -> DriveFeedback:
        """The current state as an immutable :class:`DriveFeedback` (no frames are read)."""
        now = self._clock()
        cfg = self._cfg
        age = tuple([now - t for t in self._sample_time])
        oldest = max(age)
        timeout = cfg.feedback_timeout_s
        hb_age = tuple([now - t for t in self._hb_time])
        since_start = now - self._start
        hb_timeout = cfg.heartbeat_timeout_s
        # Never heard: as old as the link.
        hb_lost = tuple([(a if a != math.inf else since_start) > hb_timeout for a in hb_age])
        if hb_lost != tuple(self._hb_lost):
            for i, lost in enumerate(hb_lost):
                if lost != self._hb_lost[i]:
                    self._hb_lost[i] = lost
                    self._event(i, "heartbeat_lost" if lost else "heartbeat_back")
        self._seq += 1
        return DriveFeedback(
            seq=self._seq,
            stamp=now,
            cycle=max(self._sync_cycle, 0),
            position_rad=self._pos,
            velocity_rad_s=self._vel,
            state=tuple(self._state),
            nmt_state=tuple(self._nmt),
            bus_off=self._bus_off,
            counters=dict(self._c),
            raw={
                "torque_nm": tuple(self._tau),
                "statusword": tuple(self._sw),
                "fresh": tuple(self._fresh),
                "age_s": age,
                "stale": tuple([a > timeout for a in age]),
                "command_missed": tuple(self._cmd_missed),
                "heartbeat_age_s": hb_age,
                "heartbeat_lost": hb_lost,
                "error_code": tuple(self._err),
                "torque_limit_nm": tuple(self._limit),
            },
            oldest_age_s=oldest,
            any_stale=oldest > timeout,
            any_heartbeat_lost=any(hb_lost),
            any_fault_bit=any(sw & _FAULT_BIT for sw in self._sw),
            oldest_heartbeat_age_s=min(max(hb_age), since_start),
        )

    def pop_events(self) -> list[LinkEvent]:
        """Events since the last call, oldest first."""
        out = list(self._events)
        self._events.clear()
        return out

    def pop_emergencies(self) -> list[Emergency]:
        """EMCY frames received since the last call, oldest first."""
        out = list(self._emcy)
        self._emcy.clear()
        return out

    # ----- sequences ---------------------------------------------------------------------------
    def run_sequence(
        self,
        target: DriveTarget | Sequence[DriveTarget],
        *,
        timeout_s: float = 0.5,
        pump: Callable[[], None] | None = None,
    ) -> DriveFeedback:
        """Cycle zero torque with sequenced controlwords until every drive reached ``target``.

        For start-up and tests, outside the control loop (inside it, call :meth:`controlwords`
        each tick instead). ``pump`` is called after each cycle's SYNC (a test steps the
        emulator and advances its clock there); without it the call sleeps one cycle.

        Raises
        ------
        DriveError
            If some drive has not reached the target within ``timeout_s`` of the link clock.
        """
        targets = (target,) * self._n if isinstance(target, DriveTarget) else tuple(target)
        start = self._clock()
        zeros = np.zeros(self._n)
        while True:
            fb = self.poll_feedback()
            pending = [
                i
                for i in range(self._n)
                if not p.target_reached(fb.state[i], targets[i]) or fb.stale[i]
            ]
            if not pending:
                return fb
            if self._clock() - start > timeout_s:
                states = ", ".join(f"{i}: {fb.state[i].name}" for i in pending)
                raise DriveError(
                    f"drives did not reach {targets[pending[0]].value} within {timeout_s:g} s "
                    f"({states})"
                )
            self.send_command(zeros, self.controlwords(targets))
            self.send_sync()
            if pump is not None:
                pump()
            else:
                time.sleep(self._cfg.cycle_period_s)
