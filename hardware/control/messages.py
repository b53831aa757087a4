"""What crosses a process or thread boundary around the control loop, each with one encoding.

- An estimate (:class:`~hapticloud.core.perception.SurfaceEstimate` without its clouds): the
  tuple of :func:`estimate_to_wire` in the pipes, the same fields named by
  :data:`ESTIMATE_WIRE_FIELDS` as a dict (:func:`estimate_to_dict`) in the recordings' estimate
  channel and in the replay. There is no other estimate encoding in the project.
- A frame time without an estimate (:func:`send_camera_frame`), for the camera watchdog.
- :class:`ControlSnapshot`: what the control loop publishes every few ticks.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

__all__ = [
    "ESTIMATE_WIRE_FIELDS",
    "ControlSnapshot",
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
    )


def estimate_from_wire(wire: tuple[Any, ...]) -> Any:
    from hapticloud.core.perception import SurfaceEstimate

    t, camera, centroid, normal, valid, quality, reason, method, seq, free_m, hip = wire
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
)


def estimate_to_dict(est: Any) -> dict[str, Any]:
    """:func:`estimate_to_wire` with its fields named (JSON-ready: tuples become lists)."""
    return {
        name: list(value) if isinstance(value, tuple) else value
        for name, value in zip(ESTIMATE_WIRE_FIELDS, estimate_to_wire(est), strict=True)
    }


def estimate_from_dict(data: Mapping[str, Any]) -> Any:
    """The estimate of :func:`estimate_to_dict`'s dict (``KeyError`` naming a missing field)."""
    return estimate_from_wire(tuple(data[name] for name in ESTIMATE_WIRE_FIELDS))


def send_estimate(conn: Any, est: Any) -> None:
    """Send an estimate down a :attr:`ControlProcess.estimate_connection` (from any process)."""
    conn.send(("estimate", estimate_to_wire(est)))


def send_camera_frame(conn: Any, camera: str, t: float) -> None:
    """Tell the loop that ``camera`` delivered a frame at ``t`` (for its watchdog)."""
    conn.send(("camera", (str(camera), float(t))))
