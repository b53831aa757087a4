"""Parameters of the drive bus, shared by the master side (:class:`~.link.DriveLink`) and the
emulated drives (:class:`~.emulator.DriveEmulator`): both must agree on rates, node ids and limits.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np
from hapticloud.core.config import StageConfig, param
from hapticloud.core.errors import ConfigError
from numpy.typing import ArrayLike

from . import protocol as p

#: Effort limits of the shipped URDF (N m), joint order; :meth:`DriveBusConfig.for_model` takes
#: them from a loaded model instead.
DEFAULT_TAU_MAX_NM = (80.0, 80.0, 80.0, 80.0, 40.0, 30.0)


class _HasTorqueLimits(Protocol):
    @property
    def tau_max(self) -> ArrayLike: ...


@dataclass(frozen=True)
class DriveBusConfig(StageConfig):
    """The drive bus: cycle rate, bit rates, node ids, torque limits and liveness timeouts.

    Cross-field rules (:meth:`check`): six torque limits inside the int16 torque field, data bit
    rate >= nominal bit rate, heartbeat timeout > heartbeat period, feedback timeout >= one cycle.
    """

    _path: ClassVar[str] = "drives"

    cycle_rate_hz: float = param(
        800.0, lo=50.0, hi=4000.0, unit="Hz", doc="command/SYNC rate (the control rate)"
    )
    nominal_bitrate: int = param(
        1_000_000, lo=10_000, hi=1_000_000, unit="bit/s", doc="CAN FD arbitration bit rate"
    )
    data_bitrate: int = param(
        5_000_000, lo=10_000, hi=12_000_000, unit="bit/s", doc="CAN FD data-phase bit rate"
    )
    bitrate_switch: bool = param(True, doc="send frames with BRS (data phase at data_bitrate)")
    first_node_id: int = param(
        1, lo=1, hi=127 - p.N_DRIVES + 1, doc="node id of drive 0; drive i is first + i", gui=False
    )
    tau_max_nm: tuple[float, ...] = param(
        DEFAULT_TAU_MAX_NM,
        lo=0.01,
        hi=160.0,
        unit="N m",
        doc="per-drive torque limit; the link clamps every command to it",
        gui=False,
    )
    heartbeat_period_s: float = param(
        0.01, lo=0.001, hi=1.0, unit="s", doc="drives' heartbeat producer period"
    )
    heartbeat_timeout_s: float = param(
        0.025, lo=0.002, hi=5.0, unit="s", doc="a drive without heartbeat for this long is lost"
    )
    feedback_timeout_s: float = param(
        0.00375,
        lo=0.0005,
        hi=0.5,
        unit="s",
        doc="a drive whose newest feedback is older than this is stale (3 cycles at 800 Hz)",
    )
    send_errors_for_bus_off: int = param(
        3, lo=1, hi=1000, doc="consecutive failed sends that count as bus-off"
    )

    def check(self) -> None:
        if len(self.tau_max_nm) != p.N_DRIVES:
            raise ConfigError(
                f"tau_max_nm: expected {p.N_DRIVES} limits, got {len(self.tau_max_nm)}"
            )
        if self.data_bitrate < self.nominal_bitrate:
            raise ConfigError(
                f"data_bitrate = {self.data_bitrate}: must be >= nominal_bitrate = "
                f"{self.nominal_bitrate}"
            )
        if not self.heartbeat_timeout_s > self.heartbeat_period_s:
            raise ConfigError(
                f"heartbeat_timeout_s = {self.heartbeat_timeout_s}: must be > "
                f"heartbeat_period_s = {self.heartbeat_period_s}"
            )
        if self.feedback_timeout_s < self.cycle_period_s:
            raise ConfigError(
                f"feedback_timeout_s = {self.feedback_timeout_s}: must be >= one cycle "
                f"({self.cycle_period_s:g} s)"
            )

    @property
    def cycle_period_s(self) -> float:
        """Control cycle period (s)."""
        return 1.0 / self.cycle_rate_hz

    @property
    def tau_max(self) -> np.ndarray:
        """Torque limits as a read-only float array (N m), shape (6,)."""
        arr = np.array(self.tau_max_nm, dtype=np.float64)
        arr.setflags(write=False)
        return arr

    def for_model(self, model: _HasTorqueLimits) -> DriveBusConfig:
        """A copy with the torque limits ``model.tau_max`` (a :class:`RobotModel`'s URDF)."""
        limits = tuple(float(x) for x in np.asarray(model.tau_max, dtype=np.float64))
        return dataclasses.replace(self, tau_max_nm=limits)
