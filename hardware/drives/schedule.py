"""Bus load of the drive schedule: frame durations at the configured bit rates, per cycle.

A frame's duration is counted in bits at the two rates of CAN FD (ISO 11898-1:2015):

- **arbitration phase** at the nominal rate: SOF, 11-bit id, RRS, IDE, FDF, res, BRS (17 bits),
  and after the data phase ACK, ACK delimiter, EOF and the 3-bit intermission (12 bits);
- **data phase** at the data rate when BRS is set: ESI, DLC, the payload, the 4-bit stuff count,
  the CRC (17 bits up to 16 bytes, 21 above), the fixed stuff bits of the CRC field (one per 4
  bits: 6 or 7) and the CRC delimiter.

Dynamic stuff bits (one after five equal bits, from SOF to the end of the data field) depend on
the data; ``stuffing="worst"`` counts the bound ``floor((L - 1) / 4)`` for ``L`` stuffed bits,
``"none"`` counts none. The true load of a real payload lies between the two; the design figure
is the worst case. A classic CAN frame is ``47 + 8 n`` bits, ``34 + 8 n`` of them stuffed.

Run ``python -m hapticloud.hardware.drives load`` for the table in docs/drive-protocol.md.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Literal, NamedTuple

from . import protocol as p
from .config import DriveBusConfig

Stuffing = Literal["worst", "none"]

_FD_ARBITRATION = 17  # SOF, id 11, RRS, IDE, FDF, res, BRS
_FD_TAIL = 12  # ACK, ACK delimiter, EOF 7, intermission 3
_CLASSIC_OVERHEAD = 47  # SOF..DLC 19, CRC 15, CRC delimiter, ACK 2, EOF 7, IFS 3
_CLASSIC_STUFFED = 34  # SOF .. end of CRC without the payload
_FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


class FrameBits(NamedTuple):
    """Bits of one frame at the nominal rate and at the data rate (stuff bits included)."""

    nominal: int
    data: int


def fd_length(payload_bytes: int) -> int:
    """Smallest CAN FD data length >= ``payload_bytes`` (0..64)."""
    for n in _FD_LENGTHS:
        if n >= payload_bytes:
            return n
    raise ValueError(f"payload_bytes = {payload_bytes}: CAN FD carries at most 64 bytes")


def _worst_stuff(bits: int) -> int:
    return (bits - 1) // 4 if bits > 0 else 0


def frame_bits(
    payload_bytes: int, *, fd: bool = True, brs: bool = True, stuffing: Stuffing = "worst"
) -> FrameBits:
    """Bit counts of one base-format (11-bit id) data frame.

    Parameters
    ----------
    payload_bytes
        Data length in bytes (a CAN FD length for ``fd``, 0..8 for classic CAN).
    fd
        CAN FD frame (else classic CAN 2.0).
    brs
        Bit rate switch: the data phase runs at the data bit rate (FD only).
    stuffing
        ``"worst"`` for the worst-case number of dynamic stuff bits, ``"none"`` for none.
    """
    n = payload_bytes
    if not fd:
        if not 0 <= n <= 8:
            raise ValueError(f"payload_bytes = {n}: classic CAN carries 0..8 bytes")
        stuff = _worst_stuff(_CLASSIC_STUFFED + 8 * n) if stuffing == "worst" else 0
        return FrameBits(_CLASSIC_OVERHEAD + 8 * n + stuff, 0)
    if fd_length(n) != n:
        raise ValueError(f"payload_bytes = {n}: not a CAN FD length {_FD_LENGTHS}")
    crc = 17 if n <= 16 else 21
    fixed_stuff = 1 + (4 + crc - 1) // 4
    data_phase = 1 + 4 + 8 * n + 4 + crc + fixed_stuff + 1  # ESI, DLC, data, SBC, CRC, FSB, delim
    stuffed = _FD_ARBITRATION + 1 + 4 + 8 * n  # SOF .. end of data field
    stuff_total = _worst_stuff(stuffed) if stuffing == "worst" else 0
    stuff_arb = _worst_stuff(_FD_ARBITRATION) if stuffing == "worst" else 0
    nominal = _FD_ARBITRATION + stuff_arb + _FD_TAIL
    data = data_phase + stuff_total - stuff_arb
    if brs:
        return FrameBits(nominal, data)
    return FrameBits(nominal + data, 0)


def frame_duration_s(
    payload_bytes: int,
    nominal_bitrate: float,
    data_bitrate: float,
    *,
    fd: bool = True,
    brs: bool = True,
    stuffing: Stuffing = "worst",
) -> float:
    """Time one frame occupies the bus (s), intermission included."""
    bits = frame_bits(payload_bytes, fd=fd, brs=brs, stuffing=stuffing)
    return bits.nominal / nominal_bitrate + bits.data / data_bitrate


class ScheduledFrame(NamedTuple):
    """One kind of frame in the schedule: ``count`` frames of ``payload_bytes`` every cycle
    (fractional for slower frames, e.g. heartbeats)."""

    name: str
    payload_bytes: int
    count_per_cycle: float
    fd: bool = True
    brs: bool = True


class LoadRow(NamedTuple):
    """One frame kind's share: single-frame duration (s) and bus time per cycle (s)."""

    name: str
    payload_bytes: int
    count_per_cycle: float
    frame_s: float
    per_cycle_s: float


class BusLoad(NamedTuple):
    """Result of :func:`bus_load`: ``load`` is bus time per cycle over the cycle period (1.0 =
    the bus is busy all the time; above 1 the schedule does not fit)."""

    load: float
    busy_per_cycle_s: float
    cycle_period_s: float
    rows: tuple[LoadRow, ...]


def drive_schedule(
    config: DriveBusConfig, *, heartbeats: bool = True
) -> tuple[ScheduledFrame, ...]:
    """The frames of this protocol per cycle: command, SYNC, six feedback frames, heartbeats.

    EMCY frames are sporadic (on faults) and NMT frames are sent at start-up; neither is counted.
    """
    brs = config.bitrate_switch
    frames = [
        ScheduledFrame("command", p.COMMAND_DLC, 1.0, brs=brs),
        ScheduledFrame("sync", p.SYNC_DLC, 1.0, brs=brs),
        ScheduledFrame("feedback", p.FEEDBACK_DLC, float(p.N_DRIVES), brs=brs),
    ]
    if heartbeats:
        per_cycle = p.N_DRIVES * config.cycle_period_s / config.heartbeat_period_s
        frames.append(ScheduledFrame("heartbeat", p.HEARTBEAT_DLC, per_cycle, brs=brs))
    return tuple(frames)


def classic_split_schedule() -> tuple[ScheduledFrame, ...]:
    """The same content on classic CAN: per drive one 4-byte RPDO (controlword, torque), a
    1-byte SYNC, and the 12-byte feedback split into an 8-byte and a 4-byte TPDO."""
    n = float(p.N_DRIVES)
    return (
        ScheduledFrame("rpdo cw+torque", 4, n, fd=False),
        ScheduledFrame("sync", 1, 1.0, fd=False),
        ScheduledFrame("tpdo pos+vel+torque", 8, n, fd=False),
        ScheduledFrame("tpdo status+counters", 4, n, fd=False),
    )


def cia402_standard_schedule() -> tuple[ScheduledFrame, ...]:
    """CiA 402's standard objects on classic CAN: per drive RPDO controlword (u16) + target torque
    (i16), TPDO statusword (u16) + position actual (i32), TPDO velocity actual (i32) + torque
    actual (i16), and an empty SYNC."""
    n = float(p.N_DRIVES)
    return (
        ScheduledFrame("rpdo 0x6040+0x6071", 4, n, fd=False),
        ScheduledFrame("sync", 0, 1.0, fd=False),
        ScheduledFrame("tpdo 0x6041+0x6064", 6, n, fd=False),
        ScheduledFrame("tpdo 0x606C+0x6077", 6, n, fd=False),
    )


def bus_load(
    frames: Iterable[ScheduledFrame],
    *,
    cycle_rate_hz: float,
    nominal_bitrate: float,
    data_bitrate: float,
    stuffing: Stuffing = "worst",
) -> BusLoad:
    """Fraction of the bus a schedule occupies at the given rates.

    Examples
    --------
    >>> cfg = DriveBusConfig()
    >>> load = bus_load(drive_schedule(cfg, heartbeats=False), cycle_rate_hz=800,
    ...                 nominal_bitrate=1e6, data_bitrate=5e6)
    >>> round(100 * load.load)
    45
    """
    period = 1.0 / cycle_rate_hz
    rows = []
    for f in frames:
        dur = frame_duration_s(
            f.payload_bytes, nominal_bitrate, data_bitrate, fd=f.fd, brs=f.brs, stuffing=stuffing
        )
        rows.append(
            LoadRow(f.name, f.payload_bytes, f.count_per_cycle, dur, dur * f.count_per_cycle)
        )
    busy = sum(r.per_cycle_s for r in rows)
    return BusLoad(busy / period, busy, period, tuple(rows))


def config_load(config: DriveBusConfig, *, stuffing: Stuffing = "worst") -> BusLoad:
    """Bus load of this protocol under ``config`` (heartbeats included): the live figure."""
    return bus_load(
        drive_schedule(config),
        cycle_rate_hz=config.cycle_rate_hz,
        nominal_bitrate=config.nominal_bitrate,
        data_bitrate=config.data_bitrate,
        stuffing=stuffing,
    )


def load_table(config: DriveBusConfig | None = None) -> list[dict[str, object]]:
    """The comparison reported in the docs: this protocol and two classic-CAN mappings, each
    with no stuffing and worst-case stuffing, at ``config``'s cycle rate."""
    cfg = config or DriveBusConfig()
    rate = cfg.cycle_rate_hz
    cases: Sequence[tuple[str, tuple[ScheduledFrame, ...], float, float]] = (
        (
            f"CAN FD {cfg.nominal_bitrate / 1e6:g}/{cfg.data_bitrate / 1e6:g} Mbit/s, cycle only",
            drive_schedule(cfg, heartbeats=False),
            cfg.nominal_bitrate,
            cfg.data_bitrate,
        ),
        (
            f"CAN FD {cfg.nominal_bitrate / 1e6:g}/{cfg.data_bitrate / 1e6:g} Mbit/s, "
            f"+ heartbeats every {cfg.heartbeat_period_s * 1e3:g} ms",
            drive_schedule(cfg),
            cfg.nominal_bitrate,
            cfg.data_bitrate,
        ),
        (
            f"CAN FD {cfg.nominal_bitrate / 1e6:g}/{cfg.nominal_bitrate / 1e6:g} Mbit/s (no BRS)",
            drive_schedule(cfg, heartbeats=False),
            cfg.nominal_bitrate,
            cfg.nominal_bitrate,
        ),
        ("classic CAN 1 Mbit/s, same content split", classic_split_schedule(), 1e6, 1e6),
        ("classic CAN 1 Mbit/s, CiA 402 standard objects", cia402_standard_schedule(), 1e6, 1e6),
    )
    out = []
    for name, frames, nominal, data in cases:
        best = bus_load(
            frames, cycle_rate_hz=rate, nominal_bitrate=nominal, data_bitrate=data, stuffing="none"
        )
        worst = bus_load(
            frames, cycle_rate_hz=rate, nominal_bitrate=nominal, data_bitrate=data, stuffing="worst"
        )
        out.append(
            {
                "case": name,
                "frames_per_cycle": round(sum(f.count_per_cycle for f in frames), 3),
                "busy_us_no_stuffing": round(best.busy_per_cycle_s * 1e6, 1),
                "busy_us_worst": round(worst.busy_per_cycle_s * 1e6, 1),
                "load_pct_no_stuffing": round(100 * best.load, 1),
                "load_pct_worst": round(100 * worst.load, 1),
            }
        )
    return out
