"""The ANYexo drive bus over python-can: a CiA 402-style cyclic synchronous torque profile on
CAN FD, its master side, an emulator of the six drives, and fault injection.

- :mod:`.protocol`: frame ids, layouts, scaling, the CiA 402 state machine (pure).
- :mod:`.codec`: ``struct`` packing of every frame; the DBC text.
- :mod:`.schedule`: frame durations and bus load at the configured bit rates.
- :mod:`.link`: :class:`DriveLink`, the master (command + SYNC out, feedback snapshots in).
- :mod:`.emulator`: :class:`DriveEmulator`, six drives and the arm they move.
- :mod:`.faults`: :class:`FaultInjector` and the bus-off wrapper :class:`InjectedBus`.

The real ANYexo drives (ANYdrive) speak EtherCAT; this layer's bus is python-can, so the transport
is whatever ``can.BusABC`` is passed in (SocketCAN, a vendor interface, or ``virtual`` in tests).
See docs/drive-protocol.md.
"""

from .config import DriveBusConfig
from .emulator import ArmDynamics, DriveEmulator, EmulatorConfig, EmulatorState, RigidArm
from .faults import FaultConfig, FaultInjector, InjectedBus
from .link import DriveFeedback, DriveLink, Emergency, LinkCounters, LinkEvent
from .protocol import DriveState, DriveTarget, EmcyCode, NmtState
from .schedule import BusLoad, bus_load, config_load, frame_duration_s

__all__ = [
    "ArmDynamics",
    "BusLoad",
    "DriveBusConfig",
    "DriveEmulator",
    "DriveFeedback",
    "DriveLink",
    "DriveState",
    "DriveTarget",
    "EmcyCode",
    "Emergency",
    "EmulatorConfig",
    "EmulatorState",
    "FaultConfig",
    "FaultInjector",
    "InjectedBus",
    "LinkCounters",
    "LinkEvent",
    "NmtState",
    "RigidArm",
    "bus_load",
    "config_load",
    "frame_duration_s",
]
