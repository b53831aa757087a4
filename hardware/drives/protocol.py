"""The drive protocol: frame identifiers, payload layouts, scaling and the CiA 402 state machine.

A CiA 402-style **cyclic synchronous torque** (CST) profile for the six drives of the exoskeleton
on one CAN FD bus (arbitration 1 Mbit/s, data phase 5 Mbit/s). Once per control cycle (800 Hz)
the master sends one command frame for all six drives, then a SYNC; on the SYNC every drive
latches the command it last received, samples its joint and answers with one feedback frame.
Heartbeats (NMT state) and EMCY frames (error code) run beside the cycle. CAN-ids follow CANopen's
pre-defined connection set, so a CANopen-aware trace tool recognises the frames:

=========  =======  ====  ===========================================================
frame      CAN-id   DLC   payload (little endian)
=========  =======  ====  ===========================================================
NMT        0x000    2     command (u8), node id (u8, 0 = all)
SYNC       0x080    1     sync counter: low byte of the command cycle (u8)
EMCY       0x080+n  8     error code (u16), error register (u8), node id (u8),
                          command cycle at the fault (u32)
COMMAND    0x100    48    cycle (u32), controlword x6 (u16), target torque x6 (i16),
                          torque limit x6 (u16), 8 reserved bytes (zero)
FEEDBACK   0x180+n  12    position (i32), velocity (i16), torque (i16), statusword (u16),
                          sync counter (u8), command counter (u8)
HEARTBEAT  0x700+n  1     NMT state (u8)
=========  =======  ====  ===========================================================

``n`` is the node id (drive index + 1 by default). The command frame takes CANopen's TIME id
(0x100), which this bus does not use: one broadcast frame instead of six RPDOs saves five frame
overheads per cycle (the reason the profile fits the bus at all, see :mod:`.schedule`). Its 40
used bytes are padded to 48, the next length CAN FD allows.

Scaling (one LSB; saturating, never wrapping):

- torque: 0.005 N m (int16: +-163.8 N m, twice the largest drive limit of 80 N m; 0.006 % of it)
- position: 1e-6 rad (int32: +-2147 rad, multi-turn)
- velocity: 1e-3 rad/s (int16: +-32.8 rad/s, over 5x the fastest joint's 6 rad/s)

The state machine is CiA 402's (figure "state machine" of IEC 61800-7-201) with the transitions a
CST drive needs; quick stop keeps the drive braking in *quick stop active* until the master
disables the voltage (quick-stop option code 6), and a fault needs the rising edge of controlword
bit 7. This module is pure (no bus): the emulator runs :func:`next_state` on the drive side, the
link runs :func:`controlword_towards` on the master side.
"""

from __future__ import annotations

from enum import Enum, IntEnum, IntFlag
from functools import lru_cache

#: Number of drives on the bus (the six joints of ANYexo's right arm).
N_DRIVES = 6

# ----- CAN identifiers (11 bit) ------------------------------------------------------------------
NMT_ID = 0x000
SYNC_ID = 0x080
EMCY_BASE_ID = 0x080
COMMAND_ID = 0x100
FEEDBACK_BASE_ID = 0x180
HEARTBEAT_BASE_ID = 0x700

# ----- payload lengths (bytes on the wire, CAN FD lengths) ---------------------------------------
NMT_DLC = 2
SYNC_DLC = 1
EMCY_DLC = 8
COMMAND_DLC = 48
#: Bytes of the command frame that carry data (the rest is zero padding up to ``COMMAND_DLC``).
COMMAND_USED = 40
FEEDBACK_DLC = 12
HEARTBEAT_DLC = 1

# ----- scaling -----------------------------------------------------------------------------------
#: Torque LSB (N m) of target torque, torque limit and measured torque.
TORQUE_LSB_NM = 0.005
#: Position LSB (rad).
POSITION_LSB_RAD = 1e-6
#: Velocity LSB (rad/s).
VELOCITY_LSB_RAD_S = 1e-3
INT16_MIN, INT16_MAX = -32768, 32767
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1
UINT16_MAX = 65535
#: Largest torque the int16 field carries (N m).
TORQUE_RANGE_NM = INT16_MAX * TORQUE_LSB_NM
#: Largest velocity the int16 field carries (rad/s).
VELOCITY_RANGE_RAD_S = INT16_MAX * VELOCITY_LSB_RAD_S


def node_id(drive: int, first_node: int = 1) -> int:
    """CANopen node id of drive index ``drive`` (0-based)."""
    return first_node + drive


# ----- NMT (CiA 301) -----------------------------------------------------------------------------
class NmtCommand(IntEnum):
    """NMT command specifiers (first byte of the NMT frame)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """NMT states as carried by the heartbeat. Drives process COMMAND and SYNC only when
    OPERATIONAL."""

    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


# ----- EMCY (CiA 301 / CiA 402 error codes) ------------------------------------------------------
class EmcyCode(IntEnum):
    """Error codes a drive reports in its EMCY frame (subset of CiA 301 / CiA 402)."""

    NO_ERROR = 0x0000  # sent after a fault reset: "error reset or no error"
    GENERIC = 0x1000
    OVERCURRENT = 0x2310  # continuous over-current, device output side
    OVERVOLTAGE = 0x3210  # DC link over-voltage
    UNDERVOLTAGE = 0x3220  # DC link under-voltage
    OVERTEMPERATURE = 0x4310  # drive temperature too high
    ENCODER = 0x7305  # incremental sensor 1 fault
    HEARTBEAT = 0x8130  # life guard or heartbeat error
    BUS_OFF_RECOVERED = 0x8140
    COMMAND_TIMEOUT = 0x8250  # RPDO timeout: no fresh command within the drive's timeout


class ErrorRegister(IntFlag):
    """Error register (object 0x1001) bits, byte 2 of the EMCY frame."""

    GENERIC = 0x01
    CURRENT = 0x02
    VOLTAGE = 0x04
    TEMPERATURE = 0x08
    COMMUNICATION = 0x10
    MANUFACTURER = 0x80


def error_register_for(code: int) -> int:
    """The error register bits that go with an EMCY error code (generic bit set for any error)."""
    if code == EmcyCode.NO_ERROR:
        return 0
    group = code & 0xF000
    bits = ErrorRegister.GENERIC
    if group == 0x2000:
        bits |= ErrorRegister.CURRENT
    elif group == 0x3000:
        bits |= ErrorRegister.VOLTAGE
    elif group == 0x4000:
        bits |= ErrorRegister.TEMPERATURE
    elif group == 0x8000:
        bits |= ErrorRegister.COMMUNICATION
    elif group in (0x7000, 0xF000):
        bits |= ErrorRegister.MANUFACTURER
    return int(bits)


# ----- CiA 402 controlword / statusword -----------------------------------------------------------
class Controlword(IntFlag):
    """Controlword (object 0x6040) bits."""

    SWITCH_ON = 0x0001
    ENABLE_VOLTAGE = 0x0002
    QUICK_STOP = 0x0004  # active low: 0 requests a quick stop
    ENABLE_OPERATION = 0x0008
    FAULT_RESET = 0x0080  # rising edge resets a fault
    HALT = 0x0100


#: Device control commands (CiA 402 table "device control commands").
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007  # also "disable operation" from operation enabled
CW_ENABLE_OPERATION = 0x000F
CW_FAULT_RESET = 0x0080


class Statusword(IntFlag):
    """Statusword (object 0x6041) bits."""

    READY_TO_SWITCH_ON = 0x0001
    SWITCHED_ON = 0x0002
    OPERATION_ENABLED = 0x0004
    FAULT = 0x0008
    VOLTAGE_ENABLED = 0x0010
    QUICK_STOP = 0x0020  # active low: 0 while quick stop is active
    SWITCH_ON_DISABLED = 0x0040
    WARNING = 0x0080
    REMOTE = 0x0200  # the drive obeys the controlword from the bus
    TARGET_REACHED = 0x0400
    FOLLOWING = 0x1000  # CST: the drive follows the target torque


class DriveState(IntEnum):
    """CiA 402 power-drive-system states."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


# Statusword bits 0-3, 5, 6 per state (CiA 402 table "state coding"); bit 4 (voltage enabled) is
# set whenever the power stage has voltage, bit 9 (remote) always.
_STATE_BITS: dict[DriveState, int] = {
    DriveState.NOT_READY_TO_SWITCH_ON: 0x0000,
    DriveState.SWITCH_ON_DISABLED: 0x0040,
    DriveState.READY_TO_SWITCH_ON: 0x0031,
    DriveState.SWITCHED_ON: 0x0033,
    DriveState.OPERATION_ENABLED: 0x1037,
    DriveState.QUICK_STOP_ACTIVE: 0x0017,
    DriveState.FAULT_REACTION_ACTIVE: 0x001F,
    DriveState.FAULT: 0x0008,
}


def statusword_of(state: DriveState, *, warning: bool = False) -> int:
    """Statusword a drive in ``state`` reports (remote bit set; warning bit on request)."""
    word = _STATE_BITS[state] | Statusword.REMOTE
    if warning:
        word |= Statusword.WARNING
    return int(word)


def state_of(statusword: int) -> DriveState:
    """Decode the CiA 402 state from a statusword (masks 0x4F / 0x6F of the standard)."""
    low = statusword & 0x4F
    if low == 0x00:
        return DriveState.NOT_READY_TO_SWITCH_ON
    if low == 0x40:
        return DriveState.SWITCH_ON_DISABLED
    if low == 0x0F:
        return DriveState.FAULT_REACTION_ACTIVE
    if low == 0x08:
        return DriveState.FAULT
    six = statusword & 0x6F
    if six == 0x21:
        return DriveState.READY_TO_SWITCH_ON
    if six == 0x23:
        return DriveState.SWITCHED_ON
    if six == 0x27:
        return DriveState.OPERATION_ENABLED
    if six == 0x07:
        return DriveState.QUICK_STOP_ACTIVE
    # Bit patterns the standard does not define: treat as a fault so that nothing enables on them.
    return DriveState.FAULT


def _is_disable_voltage(cw: int) -> bool:
    return (cw & 0x82) == 0x00


def _is_quick_stop(cw: int) -> bool:
    return (cw & 0x86) == 0x02


def _is_shutdown(cw: int) -> bool:
    return (cw & 0x87) == 0x06


def _is_switch_on(cw: int) -> bool:
    # "switch on" (0x07) and "switch on + enable operation" (0x0F) both switch on from READY.
    return (cw & 0x87) == 0x07


def _is_disable_operation(cw: int) -> bool:
    return (cw & 0x8F) == 0x07


def _is_enable_operation(cw: int) -> bool:
    return (cw & 0x8F) == 0x0F


def next_state(state: DriveState, controlword: int, previous_controlword: int) -> DriveState:
    """Drive-side transition on a latched controlword (CiA 402 transitions 2-12 and 15).

    Internal transitions are the drive's own business and not made here: 0/1 (start-up to
    SWITCH ON DISABLED), 13 (any state to FAULT REACTION ACTIVE on a fault) and 14 (FAULT
    REACTION ACTIVE to FAULT when the reaction is done).

    Parameters
    ----------
    state
        The drive's state before the controlword.
    controlword
        The controlword latched at this SYNC.
    previous_controlword
        The controlword latched at the previous SYNC (fault reset acts on a rising bit 7 edge).
    """
    cw = controlword
    if state is DriveState.FAULT:
        rising = bool(cw & Controlword.FAULT_RESET) and not (
            previous_controlword & Controlword.FAULT_RESET
        )
        return DriveState.SWITCH_ON_DISABLED if rising else state  # 15
    if state is DriveState.SWITCH_ON_DISABLED:
        return DriveState.READY_TO_SWITCH_ON if _is_shutdown(cw) else state  # 2
    if state is DriveState.READY_TO_SWITCH_ON:
        if _is_disable_voltage(cw) or _is_quick_stop(cw):
            return DriveState.SWITCH_ON_DISABLED  # 7
        return DriveState.SWITCHED_ON if _is_switch_on(cw) else state  # 3
    if state is DriveState.SWITCHED_ON:
        if _is_disable_voltage(cw) or _is_quick_stop(cw):
            return DriveState.SWITCH_ON_DISABLED  # 10
        if _is_shutdown(cw):
            return DriveState.READY_TO_SWITCH_ON  # 6
        return DriveState.OPERATION_ENABLED if _is_enable_operation(cw) else state  # 4
    if state is DriveState.OPERATION_ENABLED:
        if _is_disable_voltage(cw):
            return DriveState.SWITCH_ON_DISABLED  # 9
        if _is_quick_stop(cw):
            return DriveState.QUICK_STOP_ACTIVE  # 11
        if _is_shutdown(cw):
            return DriveState.READY_TO_SWITCH_ON  # 8
        if _is_disable_operation(cw):
            return DriveState.SWITCHED_ON  # 5
        return state
    if state is DriveState.QUICK_STOP_ACTIVE:
        # Option code 6: keep braking until the master disables the voltage (12).
        return DriveState.SWITCH_ON_DISABLED if _is_disable_voltage(cw) else state
    return state


class DriveTarget(Enum):
    """What the master wants a drive to reach; :func:`controlword_towards` sequences it."""

    #: Torque off, voltage on: READY TO SWITCH ON (from operation enabled: "shutdown").
    DISABLED = "disabled"
    #: OPERATION ENABLED through shutdown, switch on, enable operation.
    ENABLED = "enabled"
    #: Brake now: QUICK STOP ACTIVE from operation enabled, SWITCH ON DISABLED otherwise.
    QUICK_STOP = "quick_stop"
    #: Leave FAULT by a fault-reset edge; drives that are not in fault keep their state.
    FAULT_RESET = "fault_reset"


#: The controlword that keeps a drive in its state.
_HOLD: dict[DriveState, int] = {
    DriveState.NOT_READY_TO_SWITCH_ON: CW_DISABLE_VOLTAGE,
    DriveState.SWITCH_ON_DISABLED: CW_DISABLE_VOLTAGE,
    DriveState.READY_TO_SWITCH_ON: CW_SHUTDOWN,
    DriveState.SWITCHED_ON: CW_SWITCH_ON,
    DriveState.OPERATION_ENABLED: CW_ENABLE_OPERATION,
    DriveState.QUICK_STOP_ACTIVE: CW_QUICK_STOP,
    DriveState.FAULT_REACTION_ACTIVE: CW_DISABLE_VOLTAGE,
    DriveState.FAULT: CW_DISABLE_VOLTAGE,
}


@lru_cache(maxsize=1024)
def controlword_towards(state: DriveState, target: DriveTarget, previous_controlword: int) -> int:
    """Master-side sequencer: the next controlword that moves a drive from ``state`` to ``target``.

    Send it each cycle with the state from the latest feedback; the drive advances one CiA 402
    transition per SYNC. A fault is never reset unless ``target`` is FAULT_RESET, and a drive in
    quick stop is first disabled (transition 12), so ENABLED never skips a step the standard
    requires. Pure and cached: the control loop calls it six times per tick.
    """
    if target is DriveTarget.QUICK_STOP:
        return CW_QUICK_STOP
    if target is DriveTarget.FAULT_RESET:
        if state is DriveState.FAULT:
            # Alternate 0 and bit 7 so that every second cycle carries a rising edge.
            return 0 if previous_controlword & Controlword.FAULT_RESET else CW_FAULT_RESET
        return _HOLD[state]
    if state in (
        DriveState.FAULT,
        DriveState.FAULT_REACTION_ACTIVE,
        DriveState.NOT_READY_TO_SWITCH_ON,
        DriveState.QUICK_STOP_ACTIVE,
    ):
        return CW_DISABLE_VOLTAGE
    if target is DriveTarget.DISABLED:
        return CW_SHUTDOWN
    # ENABLED
    if state is DriveState.SWITCH_ON_DISABLED:
        return CW_SHUTDOWN
    if state is DriveState.READY_TO_SWITCH_ON:
        return CW_SWITCH_ON
    return CW_ENABLE_OPERATION


def target_reached(state: DriveState, target: DriveTarget) -> bool:
    """Whether ``state`` is where ``target`` leads."""
    if target is DriveTarget.ENABLED:
        return state is DriveState.OPERATION_ENABLED
    if target is DriveTarget.DISABLED:
        return state is DriveState.READY_TO_SWITCH_ON
    if target is DriveTarget.QUICK_STOP:
        return state in (DriveState.QUICK_STOP_ACTIVE, DriveState.SWITCH_ON_DISABLED)
    return state not in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE)


def torque_allowed(state: DriveState) -> bool:
    """Whether a drive in ``state`` applies the commanded torque (only OPERATION ENABLED)."""
    return state is DriveState.OPERATION_ENABLED
