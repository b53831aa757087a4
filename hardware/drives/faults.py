"""Fault injection for the drive emulator and the master's bus.

One :class:`FaultInjector` is shared by the :class:`~.emulator.DriveEmulator` (which asks it, per
frame, whether to drop or delay, and per drive whether to fault or stay silent) and, for bus-off,
by an :class:`InjectedBus` wrapped around the master's bus (whose ``send`` then fails like a
controller that went bus-off, and which delivers one SocketCAN-style bus-off error frame).

Losses are drawn from a seeded :class:`random.Random`, so a test that injects 1 % loss gets the
same frames dropped on every run, and every drop is counted (:attr:`FaultInjector.counters`), so a
test can compare what the master noticed with what was really lost.

Faults can be changed at any time from any thread: every setting is one attribute assignment,
read by the emulator on its next frame.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import can
from hapticloud.core.config import StageConfig, param
from hapticloud.core.errors import InputError

from . import protocol as p

#: SocketCAN error class of a bus-off error frame (``CAN_ERR_BUSOFF`` in ``linux/can/error.h``).
CAN_ERR_BUSOFF = 0x00000040
#: SocketCAN error class "controller restarted" (``CAN_ERR_RESTARTED``).
CAN_ERR_RESTARTED = 0x00000100

#: Frame kinds the injector counts separately.
KINDS = ("command", "sync", "nmt", "feedback", "heartbeat", "emcy", "other")


@dataclass(frozen=True)
class FaultConfig(StageConfig):
    """Initial fault settings of a :class:`FaultInjector` (all off by default)."""

    _path: ClassVar[str] = "faults"

    rx_loss_rate: float = param(
        0.0, lo=0.0, hi=1.0, doc="fraction of master frames (command, SYNC, NMT) the drives lose"
    )
    tx_loss_rate: float = param(
        0.0, lo=0.0, hi=1.0, doc="fraction of drive frames (feedback, heartbeat, EMCY) lost"
    )
    latency_s: float = param(
        0.0, lo=0.0, hi=1.0, unit="s", doc="extra delay of every frame the drives send"
    )
    jitter_s: float = param(
        0.0, lo=0.0, hi=1.0, unit="s", doc="uniform random extra delay in [0, jitter_s]"
    )
    seed: int = param(0, lo=0, hi=2**31 - 1, doc="seed of the loss and jitter draws", gui=False)


class FaultCounters(NamedTuple):
    """What the injector did so far. ``dropped`` maps a frame kind (:data:`KINDS`) to the number
    of frames lost by the loss rates; ``suppressed_heartbeats`` counts heartbeats withheld by
    heartbeat loss; ``bus_off_dropped`` frames lost because the bus was off; ``silent_dropped``
    frames a silent drive did not send or receive."""

    dropped: dict[str, int]
    suppressed_heartbeats: int
    bus_off_dropped: int
    silent_dropped: int
    drive_faults: int


#: The :class:`FaultInjector` methods another process may call by name (control process,
#: emulator process, tests).
FAULT_METHODS = (
    "set_loss",
    "set_latency",
    "inject_drive_fault",
    "clear_drive_fault",
    "set_heartbeat_loss",
    "set_silent",
    "set_bus_off",
)


class FaultInjector:
    """Mutable fault settings shared by the emulator and an :class:`InjectedBus`.

    Parameters
    ----------
    config
        Initial loss rates, latency and seed.
    n_drives
        Number of drives (indices ``0 .. n_drives - 1``).

    Examples
    --------
    >>> faults = FaultInjector(FaultConfig(tx_loss_rate=0.01, seed=3))
    >>> faults.inject_drive_fault(2, p.EmcyCode.OVERCURRENT)
    >>> faults.set_heartbeat_loss(4)
    """

    def __init__(self, config: FaultConfig | None = None, *, n_drives: int = p.N_DRIVES) -> None:
        cfg = config or FaultConfig()
        self._n = n_drives
        self._rng = random.Random(cfg.seed)
        self.rx_loss_rate = cfg.rx_loss_rate
        self.tx_loss_rate = cfg.tx_loss_rate
        self.latency_s = cfg.latency_s
        self.jitter_s = cfg.jitter_s
        self._fault_code = [0] * n_drives
        self._persistent = [False] * n_drives
        self._hb_lost = [False] * n_drives
        self._silent = [False] * n_drives
        self._bus_off = False
        self._bus_off_events = 0
        self._dropped = dict.fromkeys(KINDS, 0)
        self._suppressed_hb = 0
        self._bus_off_dropped = 0
        self._silent_dropped = 0
        self._drive_faults = 0

    # ----- settings ------------------------------------------------------------------------------
    def _drive(self, drive: int) -> int:
        if not 0 <= drive < self._n:
            raise InputError(f"drive: expected 0..{self._n - 1}, got {drive}")
        return drive

    def _drives(self, drive: int | None) -> range | tuple[int]:
        return range(self._n) if drive is None else (self._drive(drive),)

    def set_loss(self, rx: float | None = None, tx: float | None = None) -> None:
        """Set the loss rates (fractions in [0, 1]) of master frames (``rx``) and drive frames
        (``tx``); ``None`` keeps a rate."""
        for name, value in (("rx", rx), ("tx", tx)):
            if value is not None and not 0.0 <= value <= 1.0:
                raise InputError(f"{name}: loss rate must be in [0, 1], got {value}")
        if rx is not None:
            self.rx_loss_rate = float(rx)
        if tx is not None:
            self.tx_loss_rate = float(tx)

    def set_latency(self, latency_s: float, jitter_s: float = 0.0) -> None:
        """Delay every drive frame by ``latency_s`` plus a uniform draw in ``[0, jitter_s]`` (s)."""
        if not (latency_s >= 0.0 and jitter_s >= 0.0):
            raise InputError(f"latency_s, jitter_s: must be >= 0, got {latency_s}, {jitter_s}")
        self.latency_s = float(latency_s)
        self.jitter_s = float(jitter_s)

    def inject_drive_fault(
        self, drive: int, code: int = p.EmcyCode.OVERCURRENT, *, persistent: bool = False
    ) -> None:
        """Make ``drive`` fault: it enters FAULT REACTION ACTIVE, sets the statusword fault bit,
        sends an EMCY with ``code`` and drops its torque. A non-persistent fault clears with the
        master's fault reset; a persistent one comes back after every reset until
        :meth:`clear_drive_fault`."""
        if not 0 < code <= 0xFFFF:
            raise InputError(f"code: expected an error code 0x0001..0xFFFF, got {code}")
        self._fault_code[self._drive(drive)] = int(code)
        self._persistent[drive] = persistent

    def clear_drive_fault(self, drive: int) -> None:
        """Remove the cause of an injected fault (the drive still needs a fault reset)."""
        self._fault_code[self._drive(drive)] = 0
        self._persistent[drive] = False

    def set_heartbeat_loss(self, drive: int | None = None, lost: bool = True) -> None:
        """Withhold the heartbeats of ``drive`` (all drives for ``None``); feedback continues."""
        for i in self._drives(drive):
            self._hb_lost[i] = lost

    def set_silent(self, drive: int | None = None, silent: bool = True) -> None:
        """Disconnect ``drive`` (all for ``None``): it neither receives nor sends, so it stops
        answering and, once enabled, faults on its command timeout."""
        for i in self._drives(drive):
            self._silent[i] = silent

    def set_bus_off(self, off: bool = True) -> None:
        """Take the bus off (no frame passes in either direction; the master's
        :class:`InjectedBus` fails its sends) or bring it back."""
        if off and not self._bus_off:
            self._bus_off_events += 1
        self._bus_off = off

    # ----- queries (emulator side) ---------------------------------------------------------------
    @property
    def bus_off(self) -> bool:
        """Whether the bus is off."""
        return self._bus_off

    @property
    def bus_off_events(self) -> int:
        """How many times the bus went off."""
        return self._bus_off_events

    def take_drive_fault(self, drive: int) -> int:
        """The injected fault code of ``drive`` (0 if none); consumes a non-persistent fault."""
        code = self._fault_code[drive]
        if code:
            self._drive_faults += 1
            if not self._persistent[drive]:
                self._fault_code[drive] = 0
        return code

    def fault_active(self, drive: int) -> bool:
        """Whether an injected fault of ``drive`` is still there (not yet taken or persistent)."""
        return self._fault_code[drive] != 0

    def heartbeat_suppressed(self, drive: int) -> bool:
        """Whether the heartbeat of ``drive`` is withheld now (counted)."""
        if self._hb_lost[drive]:
            self._suppressed_hb += 1
            return True
        return False

    def is_silent(self, drive: int) -> bool:
        """Whether ``drive`` is disconnected."""
        return self._silent[drive]

    def count_silent(self) -> None:
        """Record one frame not sent or received by a silent drive."""
        self._silent_dropped += 1

    def count_bus_off(self) -> None:
        """Record one frame lost because the bus is off."""
        self._bus_off_dropped += 1

    def drop_rx(self, kind: str) -> bool:
        """Draw whether a master frame of ``kind`` is lost (counted when it is)."""
        if self.rx_loss_rate > 0.0 and self._rng.random() < self.rx_loss_rate:
            self._dropped[kind] += 1
            return True
        return False

    def drop_tx(self, kind: str) -> bool:
        """Draw whether a drive frame of ``kind`` is lost (counted when it is)."""
        if self.tx_loss_rate > 0.0 and self._rng.random() < self.tx_loss_rate:
            self._dropped[kind] += 1
            return True
        return False

    def delay(self) -> float:
        """Extra delay (s) for one drive frame."""
        if self.jitter_s > 0.0:
            return self.latency_s + self._rng.uniform(0.0, self.jitter_s)
        return self.latency_s

    @property
    def counters(self) -> FaultCounters:
        """Counts of everything injected so far."""
        return FaultCounters(
            dict(self._dropped),
            self._suppressed_hb,
            self._bus_off_dropped,
            self._silent_dropped,
            self._drive_faults,
        )

    def wrap(self, bus: can.BusABC) -> InjectedBus:
        """Wrap the master's bus so that injected bus-off shows there too."""
        return InjectedBus(bus, self)


class InjectedBus(can.BusABC):
    """A bus wrapper whose ``send`` fails and whose ``state`` is ERROR while the injector's bus is
    off; on going off it delivers one error frame with the SocketCAN bus-off class, as a
    SocketCAN interface with error frames enabled does.

    Shutting the wrapper down shuts the wrapped bus down.
    """

    def __init__(self, inner: can.BusABC, faults: FaultInjector, **kwargs: Any) -> None:
        self._inner = inner
        self._faults = faults
        self._reported = faults.bus_off_events
        self.channel_info = f"fault-injected {getattr(inner, 'channel_info', inner)}"
        self._can_protocol = inner.protocol
        super().__init__(channel=getattr(inner, "channel", None), **kwargs)

    @property
    def inner(self) -> can.BusABC:
        """The wrapped bus."""
        return self._inner

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._faults.bus_off:
            raise can.CanOperationError("bus-off: transmit failed (injected)")
        self._inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        faults = self._faults
        if faults.bus_off_events != self._reported and faults.bus_off:
            self._reported = faults.bus_off_events
            err = can.Message(
                arbitration_id=CAN_ERR_BUSOFF,
                is_error_frame=True,
                dlc=8,
                data=bytes(8),
                check=False,
            )
            return err, False
        msg = self._inner.recv(timeout)
        if msg is not None and faults.bus_off:
            return None, False
        return msg, False

    @property
    def state(self) -> can.BusState:
        return can.BusState.ERROR if self._faults.bus_off else self._inner.state

    def shutdown(self) -> None:
        super().shutdown()
        self._inner.shutdown()
