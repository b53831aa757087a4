"""Pack and unpack the drive frames with precompiled :class:`struct.Struct` objects.

The hot path (one command, six feedback frames per 800 Hz cycle) uses :func:`encode_command` and
:func:`decode_feedback`; both work on Python ints and floats, not numpy, because ``struct`` with a
handful of scalars is faster than building arrays for six values. Every physical value is
converted with the scaling of :mod:`.protocol` and **saturates** at the field's range (a torque
of 1000 N m is sent as the largest representable torque, never wrapped to a negative one).

:func:`dbc_text` describes the same frames as a DBC; ``assets/can/anyexo_drives.dbc`` is its
output (``python -m hapticloud.hardware.drives dbc PATH`` regenerates it), and the tests check
that cantools decodes what this module packs.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

from hapticloud.assets import asset_path
from hapticloud.core.errors import InputError

from . import protocol as p

COMMAND = struct.Struct("<I6H6h6H8x")
FEEDBACK = struct.Struct("<ihhHBB")
EMCY = struct.Struct("<HBBI")
SYNC = struct.Struct("<B")
HEARTBEAT = struct.Struct("<B")
NMT = struct.Struct("<BB")

assert COMMAND.size == p.COMMAND_DLC and FEEDBACK.size == p.FEEDBACK_DLC
assert EMCY.size == p.EMCY_DLC

_TORQUE_SCALE = 1.0 / p.TORQUE_LSB_NM
_POSITION_SCALE = 1.0 / p.POSITION_LSB_RAD
_VELOCITY_SCALE = 1.0 / p.VELOCITY_LSB_RAD_S


# ----- scalar conversions ------------------------------------------------------------------------
def _saturate(value: float, scale: float, lo: int, hi: int) -> int:
    # NaN maps to 0: a corrupt number must never become a full-scale command.
    if value != value:
        return 0
    x = value * scale
    if x >= hi:
        return hi
    if x <= lo:
        return lo
    return round(x)


def torque_to_raw(torque_nm: float) -> int:
    """Torque (N m) to int16 counts, saturating."""
    return _saturate(torque_nm, _TORQUE_SCALE, p.INT16_MIN, p.INT16_MAX)


def torque_limit_to_raw(limit_nm: float) -> int:
    """Torque limit (N m, >= 0) to uint16 counts, rounded down so the limit never grows.

    Saturating: a limit beyond the field (``inf``, or so large that its count overflows a float)
    is the largest count. NaN and limits <= 0 are 0, the safe limit (the drive clamps every target
    to zero torque); :class:`~.config.DriveBusConfig` refuses non-finite limits in the first place.
    """
    if not limit_nm > 0.0:  # also NaN
        return 0
    x = limit_nm * _TORQUE_SCALE + 1e-9
    if x >= p.UINT16_MAX:  # before floor(): floor(inf) raises
        return p.UINT16_MAX
    return math.floor(x)


def position_to_raw(position_rad: float) -> int:
    """Position (rad) to int32 counts, saturating."""
    return _saturate(position_rad, _POSITION_SCALE, p.INT32_MIN, p.INT32_MAX)


def velocity_to_raw(velocity_rad_s: float) -> int:
    """Velocity (rad/s) to int16 counts, saturating."""
    return _saturate(velocity_rad_s, _VELOCITY_SCALE, p.INT16_MIN, p.INT16_MAX)


# ----- decoded frames ----------------------------------------------------------------------------
class CommandFrame(NamedTuple):
    """A decoded command frame (drive side).

    ``torque_nm`` and ``torque_limit_nm`` in N m, one per drive; ``controlword`` raw words.
    """

    cycle: int
    controlword: tuple[int, ...]
    torque_nm: tuple[float, ...]
    torque_limit_nm: tuple[float, ...]


class FeedbackFrame(NamedTuple):
    """A decoded feedback frame of one drive.

    ``position_rad`` (rad), ``velocity_rad_s`` (rad/s), ``torque_nm`` (N m), the raw
    ``statusword``, the SYNC counter it answers and the low byte of the command cycle the drive
    had latched at that SYNC (they differ when the command frame of that cycle was lost).
    """

    position_rad: float
    velocity_rad_s: float
    torque_nm: float
    statusword: int
    sync_counter: int
    command_counter: int


class Emergency(NamedTuple):
    """A decoded EMCY frame: ``code`` (CiA 301/402 error code), error ``register``, ``node`` id
    and the command ``cycle`` the drive had latched when it faulted."""

    code: int
    register: int
    node: int
    cycle: int


# ----- encoders / decoders -----------------------------------------------------------------------
def encode_command(
    cycle: int,
    controlwords: Sequence[int],
    torques_nm: Sequence[float],
    torque_limits_nm: Sequence[float],
) -> bytes:
    """Pack the 48-byte command frame.

    Parameters
    ----------
    cycle
        Cycle counter (taken modulo 2**32).
    controlwords
        Six controlwords (0..65535).
    torques_nm
        Six target torques (N m), saturated at +-163.8 N m; clamp to the drive limits before.
    torque_limits_nm
        Six torque limits (N m) the drives clamp the target to (rounded down to the LSB).
    """
    raw_t = [torque_to_raw(float(t)) for t in torques_nm]
    raw_l = [torque_limit_to_raw(float(x)) for x in torque_limits_nm]
    try:
        return COMMAND.pack(cycle & 0xFFFFFFFF, *controlwords, *raw_t, *raw_l)
    except struct.error as err:
        raise InputError(f"command frame: {err} (six controlwords 0..65535 expected)") from None


def encode_command_raw(
    cycle: int, controlwords: Sequence[int], torques: Sequence[int], limits: Sequence[int]
) -> bytes:
    """Pack the command frame from raw counts (no scaling; for tests and the emulator)."""
    return COMMAND.pack(cycle & 0xFFFFFFFF, *controlwords, *torques, *limits)


def decode_command(data: bytes | bytearray) -> CommandFrame:
    """Unpack a command frame (raises :class:`struct.error` on a wrong length)."""
    v = COMMAND.unpack_from(data)
    lsb = p.TORQUE_LSB_NM
    return CommandFrame(
        v[0],
        v[1:7],
        tuple(x * lsb for x in v[7:13]),
        tuple(x * lsb for x in v[13:19]),
    )


def encode_feedback(
    position_rad: float,
    velocity_rad_s: float,
    torque_nm: float,
    statusword: int,
    sync_counter: int,
    command_counter: int,
) -> bytes:
    """Pack one drive's 12-byte feedback frame (values saturate at their field's range)."""
    return FEEDBACK.pack(
        position_to_raw(position_rad),
        velocity_to_raw(velocity_rad_s),
        torque_to_raw(torque_nm),
        statusword & 0xFFFF,
        sync_counter & 0xFF,
        command_counter & 0xFF,
    )


def decode_feedback(data: bytes | bytearray) -> FeedbackFrame:
    """Unpack one feedback frame into SI units."""
    pos, vel, tau, sw, sync, cmd = FEEDBACK.unpack_from(data)
    return FeedbackFrame(
        pos * p.POSITION_LSB_RAD,
        vel * p.VELOCITY_LSB_RAD_S,
        tau * p.TORQUE_LSB_NM,
        sw,
        sync,
        cmd,
    )


def encode_emcy(code: int, register: int, node: int, cycle: int) -> bytes:
    """Pack an EMCY frame."""
    return EMCY.pack(code & 0xFFFF, register & 0xFF, node & 0xFF, cycle & 0xFFFFFFFF)


def decode_emcy(data: bytes | bytearray) -> Emergency:
    """Unpack an EMCY frame."""
    return Emergency(*EMCY.unpack_from(data))


def encode_sync(counter: int) -> bytes:
    """Pack a SYNC frame (counter = low byte of the command cycle)."""
    return SYNC.pack(counter & 0xFF)


def encode_heartbeat(state: int) -> bytes:
    """Pack a heartbeat frame carrying the NMT state."""
    return HEARTBEAT.pack(state & 0xFF)


def encode_nmt(command: int, node: int) -> bytes:
    """Pack an NMT command (``node`` 0 addresses every node)."""
    return NMT.pack(command & 0xFF, node & 0xFF)


# ----- DBC ---------------------------------------------------------------------------------------
class _Sig(NamedTuple):
    name: str
    start: int
    length: int
    signed: bool = False
    scale: float = 1.0
    unit: str = ""
    comment: str = ""
    values: dict[int, str] | None = None


class _Msg(NamedTuple):
    frame_id: int
    name: str
    dlc: int
    sender: str
    receivers: tuple[str, ...]
    signals: tuple[_Sig, ...]
    comment: str


def _dbc_messages(first_node: int) -> list[_Msg]:
    drives = tuple(f"Drive{i + 1}" for i in range(p.N_DRIVES))
    lsb_t, lsb_q, lsb_v = p.TORQUE_LSB_NM, p.POSITION_LSB_RAD, p.VELOCITY_LSB_RAD_S
    nmt_states = {int(s): s.name for s in p.NmtState}
    nmt_commands = {int(c): c.name for c in p.NmtCommand}
    codes = {int(c): c.name for c in p.EmcyCode}
    cmd = [_Sig("CycleCounter", 0, 32, comment="command cycle counter (u32, wraps)")]
    cmd += [
        _Sig(f"Controlword{i + 1}", 32 + 16 * i, 16, comment="CiA 402 controlword (0x6040)")
        for i in range(p.N_DRIVES)
    ]
    cmd += [
        _Sig(
            f"TargetTorque{i + 1}",
            128 + 16 * i,
            16,
            True,
            lsb_t,
            "Nm",
            "target torque (0x6071), applied from the next SYNC",
        )
        for i in range(p.N_DRIVES)
    ]
    cmd += [
        _Sig(
            f"TorqueLimit{i + 1}",
            224 + 16 * i,
            16,
            False,
            lsb_t,
            "Nm",
            "max torque (0x6072): the drive clamps the target to it",
        )
        for i in range(p.N_DRIVES)
    ]
    out = [
        _Msg(
            p.NMT_ID,
            "NMT",
            p.NMT_DLC,
            "Master",
            drives,
            (
                _Sig("NmtCommand", 0, 8, values=nmt_commands),
                _Sig("NmtNode", 8, 8, comment="node id, 0 = all nodes"),
            ),
            "CiA 301 network management",
        ),
        _Msg(
            p.SYNC_ID,
            "Sync",
            p.SYNC_DLC,
            "Master",
            drives,
            (_Sig("SyncCounter", 0, 8, comment="low byte of the command cycle"),),
            "drives latch the last command and sample their joint on it; every cycle",
        ),
        _Msg(
            p.COMMAND_ID,
            "Command",
            p.COMMAND_DLC,
            "Master",
            drives,
            tuple(cmd),
            "CST command for all six drives, every cycle before SYNC; bytes 40-47 reserved (0)",
        ),
    ]
    for i in range(p.N_DRIVES):
        n, node = i + 1, first_node + i
        out.append(
            _Msg(
                p.EMCY_BASE_ID + node,
                f"Emcy{n}",
                p.EMCY_DLC,
                drives[i],
                ("Master",),
                (
                    _Sig(
                        f"ErrorCode{n}",
                        0,
                        16,
                        comment="CiA 301/402 error code; 0 = reset",
                        values=codes,
                    ),
                    _Sig(f"ErrorRegister{n}", 16, 8, comment="object 0x1001"),
                    _Sig(f"EmcyNode{n}", 24, 8, comment="node id of the sender"),
                    _Sig(f"EmcyCycle{n}", 32, 32, comment="command cycle latched at the fault"),
                ),
                "emergency: on a fault, and with code 0 after its reset",
            )
        )
    for i in range(p.N_DRIVES):
        n, node = i + 1, first_node + i
        out.append(
            _Msg(
                p.FEEDBACK_BASE_ID + node,
                f"Feedback{n}",
                p.FEEDBACK_DLC,
                drives[i],
                ("Master",),
                (
                    _Sig(f"Position{n}", 0, 32, True, lsb_q, "rad"),
                    _Sig(f"Velocity{n}", 32, 16, True, lsb_v, "rad/s"),
                    _Sig(f"Torque{n}", 48, 16, True, lsb_t, "Nm", "measured joint torque"),
                    _Sig(f"Statusword{n}", 64, 16, comment="CiA 402 statusword (0x6041)"),
                    _Sig(f"SyncCounter{n}", 80, 8, comment="the SYNC this sample answers"),
                    _Sig(
                        f"CommandCounter{n}",
                        88,
                        8,
                        comment="low byte of the command cycle latched at that SYNC",
                    ),
                ),
                "sampled at SYNC and sent right after it; every cycle",
            )
        )
    for i in range(p.N_DRIVES):
        n, node = i + 1, first_node + i
        out.append(
            _Msg(
                p.HEARTBEAT_BASE_ID + node,
                f"Heartbeat{n}",
                p.HEARTBEAT_DLC,
                drives[i],
                ("Master",),
                (_Sig(f"NmtState{n}", 0, 8, values=nmt_states),),
                "heartbeat: NMT state at the producer period",
            )
        )
    return out


def default_dbc_path() -> Path:
    """Path of the shipped DBC (``hapticloud.assets/can/anyexo_drives.dbc``)."""
    return asset_path("can", "anyexo_drives.dbc")


def _num(x: float) -> str:
    return f"{x:.10g}"


def dbc_text(first_node: int = 1) -> str:
    """The frames of :mod:`.protocol` as DBC text (what ``assets/can/anyexo_drives.dbc`` holds).

    Nodes ``Master`` and ``Drive1`` .. ``Drive6``; signal names carry the drive number
    (``TargetTorque3``, ``Position3``). The CAN FD frames are marked with the usual
    ``VFrameFormat`` / ``CANFD_BRS`` attributes, so cantools and SavvyCAN treat them as FD.
    """
    msgs = _dbc_messages(first_node)
    drives = " ".join(f"Drive{i + 1}" for i in range(p.N_DRIVES))
    lines = [
        'VERSION "hapticloud anyexo drives 1"',
        "",
        "NS_ :",
        "\tCM_",
        "\tBA_DEF_",
        "\tBA_",
        "\tVAL_",
        "\tBA_DEF_DEF_",
        "",
        "BS_:",
        "",
        f"BU_: Master {drives}",
        "",
    ]
    for m in msgs:
        lines.append(f"BO_ {m.frame_id} {m.name}: {m.dlc} {m.sender}")
        for s in m.signals:
            sign = "-" if s.signed else "+"
            if s.signed:
                lo, hi = -(2 ** (s.length - 1)), 2 ** (s.length - 1) - 1
            else:
                lo, hi = 0, 2**s.length - 1
            lines.append(
                f" SG_ {s.name} : {s.start}|{s.length}@1{sign} ({_num(s.scale)},0) "
                f'[{_num(lo * s.scale)}|{_num(hi * s.scale)}] "{s.unit}" {",".join(m.receivers)}'
            )
        lines.append("")
    lines.append(
        'CM_ "ANYexo drive bus: CiA 402-style cyclic synchronous torque over CAN FD '
        '(1 Mbit/s arbitration, 5 Mbit/s data). See docs/drive-protocol.md.";'
    )
    lines.append('CM_ BU_ Master "control computer (hapticloud DriveLink)";')
    for i in range(p.N_DRIVES):
        lines.append(f'CM_ BU_ Drive{i + 1} "joint drive {i + 1}, node id {first_node + i}";')
    for m in msgs:
        lines.append(f'CM_ BO_ {m.frame_id} "{m.comment}";')
        for s in m.signals:
            if s.comment:
                lines.append(f'CM_ SG_ {m.frame_id} {s.name} "{s.comment}";')
    lines += [
        'BA_DEF_  "BusType" STRING ;',
        'BA_DEF_ BO_  "VFrameFormat" ENUM  "StandardCAN","ExtendedCAN","reserved","J1939PG",'
        '"reserved","reserved","reserved","reserved","reserved","reserved","reserved",'
        '"reserved","reserved","reserved","StandardCAN_FD","ExtendedCAN_FD";',
        'BA_DEF_ BO_  "CANFD_BRS" ENUM  "0","1";',
        'BA_DEF_DEF_  "BusType" "CAN FD";',
        'BA_DEF_DEF_  "VFrameFormat" "StandardCAN";',
        'BA_DEF_DEF_  "CANFD_BRS" "1";',
        'BA_ "BusType" "CAN FD";',
    ]
    for m in msgs:
        lines.append(f'BA_ "VFrameFormat" BO_ {m.frame_id} 14;')
    for m in msgs:
        for s in m.signals:
            if s.values:
                pairs = " ".join(f'{k} "{v}"' for k, v in sorted(s.values.items(), reverse=True))
                lines.append(f"VAL_ {m.frame_id} {s.name} {pairs} ;")
    return "\n".join(lines) + "\n"
