"""What crosses a process or thread boundary around the control loop, each with one encoding.

- An estimate (:class:`~hapticloud.core.perception.SurfaceEstimate` without its clouds): the
  tuple of :func:`estimate_to_wire` in the pipes, the same fields named by
  :data:`ESTIMATE_WIRE_FIELDS` as a dict (:func:`estimate_to_dict`) in the recordings' estimate
  channel and in the replay. There is no other estimate encoding in the project.
- A frame time without an estimate (:func:`send_camera_frame`), for the camera watchdog.
- The parent's commands to the loop (:data:`Command`: :class:`Enable`, :class:`Disable`,
  :class:`EmergencyStop`, :class:`Reset`, :class:`Configure`, :class:`InjectFault`,
  :class:`Stop`) and the loop's replies (:class:`ControlSnapshot` every few ticks, :class:`Ready`
  once its loop runs, :class:`Result` when it stopped, :class:`ChildFailed` when it raised): frozen
  objects, pickled through the pipes as they are.
- :class:`ControlConfig`: everything the control process is built from, checked in the parent.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple

import numpy as np

__all__ = [
    "ESTIMATE_WIRE_FIELDS",
    "ChildFailed",
    "Command",
    "Configure",
    "ControlConfig",
    "ControlSnapshot",
    "Disable",
    "EmergencyStop",
    "Enable",
    "InjectFault",
    "Ready",
    "Reset",
    "Result",
    "Stop",
    "estimate_from_dict",
    "estimate_from_wire",
    "estimate_to_dict",
    "estimate_to_wire",
    "send_camera_frame",
    "send_estimate",
]


class ControlSnapshot(NamedTuple):
    """What the control process publishes every ``snapshot_every`` ticks (small, picklable).

    Times are :func:`time.monotonic` seconds (system-wide). ``force_n`` is the constraint force at
    the HIP: the Cartesian force whose ``J^T f`` is the torque beyond transparency
    (``tau_sent - h``), least squares. ``events`` are the session transitions, watchdog
    reaction changes and configuration results no earlier snapshot carried, oldest first, up to
    eight (the rest follow in the next snapshots; those left when the loop stops come in one
    last snapshot, received by :meth:`ControlProcess.stop`): ``(t, kind, text)`` with kind
    ``"state"``, ``"reaction"``, ``"space"`` or ``"config"``.
    """

    seq: int
    tick: int
    t: float
    state: str
    reaction: str
    reaction_source: str
    reaction_reason: str
    q: tuple[float, ...]
    qd: tuple[float, ...]
    tau_sent: tuple[float, ...]
    hip_m: tuple[float, float, float]
    force_n: tuple[float, float, float]
    d_proj_m: float
    min_d_proj_m: float
    approach_mps: float
    fused_valid: bool
    estimate_age_s: float
    camera_age_s: tuple[tuple[str, float], ...]
    tick_us: float
    tick_us_max: float
    control_rate_hz: float
    misses: int
    dropped_snapshots: int
    bus_load: float
    events: tuple[tuple[float, str, str], ...]
    #: What the tick knows of the space around the HIP (``known``, ``holding``, ``stopped``:
    #: :class:`~hapticloud.core.haptics.unknown.SpaceState`) and why.
    space: str = "known"
    space_reason: str = ""
    #: Simulated time per wall time of the simulated drives' clock (NaN: real drives, or drives
    #: on wall time): below 1 the machine cannot keep up and the simulation runs slower.
    sim_time_factor: float = math.nan


def estimate_to_wire(est: Any) -> tuple[Any, ...]:
    """The part of a :class:`~hapticloud.core.perception.SurfaceEstimate` the fusion needs, as a
    small tuple (the full estimate carries clouds and does not pickle its timing table)."""
    return (
        float(est.t),
        str(est.camera),
        tuple(float(x) for x in est.centroid),
        tuple(float(x) for x in est.normal),
        bool(est.valid),
        float(est.quality),
        str(est.reason),
        str(est.method),
        int(est.seq),
        float(est.free_m),
        None if est.hip is None else tuple(float(x) for x in est.hip),
        float(est.residual_m),
    )


def estimate_from_wire(wire: tuple[Any, ...]) -> Any:
    from hapticloud.core.perception import SurfaceEstimate

    t, camera, centroid, normal, valid, quality, reason, method, seq, free_m, hip, residual_m = wire
    return SurfaceEstimate(
        t,
        camera,
        np.array(centroid),
        np.array(normal),
        valid,
        reason=reason,
        method=method,
        quality=quality,
        seq=seq,
        free_m=free_m,
        hip=None if hip is None else np.array(hip),
        residual_m=residual_m,
    )


#: The names of :func:`estimate_to_wire`'s fields, in order: the same information as a dict
#: (the recordings' estimate channel, JSON), so that there is one estimate encoding.
ESTIMATE_WIRE_FIELDS = (
    "t",
    "camera",
    "centroid",
    "normal",
    "valid",
    "quality",
    "reason",
    "method",
    "seq",
    "free_m",
    "hip",
    "residual_m",
)

#: Fields a recording made before they existed may lack, with what their absence means
#: (``residual_m`` 0: the fit's noise is unknown, so the fusion weighs the camera like the others).
_ESTIMATE_FIELDS_ADDED = {"residual_m": 0.0}


def estimate_to_dict(est: Any) -> dict[str, Any]:
    """:func:`estimate_to_wire` with its fields named (JSON-ready: tuples become lists)."""
    return {
        name: list(value) if isinstance(value, tuple) else value
        for name, value in zip(ESTIMATE_WIRE_FIELDS, estimate_to_wire(est), strict=True)
    }


def estimate_from_dict(data: Mapping[str, Any]) -> Any:
    """The estimate of :func:`estimate_to_dict`'s dict (``KeyError`` naming a missing field)."""
    return estimate_from_wire(
        tuple(
            data[name] if name not in _ESTIMATE_FIELDS_ADDED else data.get(name, default)
            for name in ESTIMATE_WIRE_FIELDS
            for default in (_ESTIMATE_FIELDS_ADDED.get(name),)
        )
    )


def send_estimate(conn: Any, est: Any) -> None:
    """Send an estimate down a :attr:`ControlProcess.estimate_connection` (from any process)."""
    conn.send(("estimate", estimate_to_wire(est)))


def send_camera_frame(conn: Any, camera: str, t: float) -> None:
    """Tell the loop that ``camera`` delivered a frame at ``t`` (for its watchdog)."""
    conn.send(("camera", (str(camera), float(t))))


# ----- parent -> loop: the commands (one pipe, read by the loop without waiting) ------------------
@dataclass(frozen=True)
class Enable:
    """Apply torque: READY -> ENABLED (refused by the session from anywhere else)."""

    name: ClassVar[str] = "enable"
    reason: str = "enable requested"


@dataclass(frozen=True)
class Disable:
    """Torque off, drives disabled: ENABLED -> READY."""

    name: ClassVar[str] = "disable"
    reason: str = "disable requested"


@dataclass(frozen=True)
class EmergencyStop:
    """Quick stop from any state."""

    name: ClassVar[str] = "estop"
    reason: str = "emergency stop"


@dataclass(frozen=True)
class Reset:
    """Clear a FAULT or EMERGENCY_STOP: fault-reset controlwords first, decided when the drives'
    fault bits cleared (refused once the reset ticks are spent)."""

    name: ClassVar[str] = "reset"


@dataclass(frozen=True)
class Configure:
    """New haptics (:class:`~hapticloud.core.loop.HapticsConfig`), fusion
    (:class:`~hapticloud.core.fusion.FusionConfig`) and/or controller
    (:class:`~hapticloud.core.control.ControllerConfig`, refused while ENABLED); ``None``: keep."""

    name: ClassVar[str] = "configure"
    haptics: Any = None
    fusion: Any = None
    controller: Any = None


@dataclass(frozen=True)
class InjectFault:
    """Call ``method`` (one of :data:`~..drives.faults.FAULT_METHODS`) of the drive emulator's
    fault injector with these arguments."""

    name: ClassVar[str] = "inject"
    method: str
    args: tuple[Any, ...] = ()
    kwargs: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Stop:
    """End the loop (torque off, drives disabled on the way out)."""

    name: ClassVar[str] = "stop"


Command = Enable | Disable | EmergencyStop | Reset | Configure | InjectFault | Stop


# ----- loop -> parent: the replies (besides the snapshots) ---------------------------------------
@dataclass(frozen=True)
class Ready:
    """The loop runs: its start-up facts (pid, scheduling, CPU, memory lock, emulator, bus,
    cameras, torque limits) as :meth:`ControlProcess.start` returns them."""

    info: Mapping[str, Any]


@dataclass(frozen=True)
class Result:
    """The loop stopped: its log and statistics, as :meth:`ControlProcess.stop` returns them."""

    result: Mapping[str, Any]


@dataclass(frozen=True)
class ChildFailed:
    """The control process raised: its traceback."""

    traceback: str


# ----- what the control process is built from --------------------------------------------------
@dataclass(frozen=True)
class ControlConfig:
    """Everything the control process is built from, checked by
    :class:`~hapticloud.hardware.control.process.ControlProcess` (where each field and its
    default is documented)."""

    scene: str
    overrides: Mapping[str, Any] | None
    period_s: float
    fifo_priority: int | None
    spin_s: float
    emulator: str
    snapshot_every: int
    log_ticks: int
    duration_s: float | None
    cpu: int | None
    #: A :class:`~hapticloud.hardware.session.WatchdogConfig` (``None``: its defaults).
    watchdogs: Any
    damping_nms: float
    dynamics: Any
    bus_timing: bool
    sim_clock: bool
