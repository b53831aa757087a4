"""A synthetic recording: a wall, a HIP that approaches and leaves it, faults, holds and stops.

:func:`synthesize` writes, with the real :class:`~.writer.RecordingWriter`, a recording whose
content is known in closed form: two cameras look at the wall ``x = 0`` (normal ``+x``); the HIP
moves along ``x`` as ``x(t) = r_hip + gap(t)`` with ``gap`` between 1 mm (contact) and 100 mm,
one period every ``period_s``; each frame's depth is ray-cast exactly into the stored rectangle
(:func:`~hapticloud.core.recording.storage_roi`), its estimate is the exact closest point
(the HIP's projection on the wall); the control state runs at 100 Hz with the space ``holding``
and ``stopped`` and the session in ``fault`` at given times, and the events say so.

For tests and benchmarks (a 10-minute recording in a minute, without the simulator); the log
clock is ``"scene"`` seconds from 0, the writer's flush timer runs on it (a chunk per 0.5 s, as
a real-time session's).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hapticloud.core.camera import CameraIntrinsics, DepthFrame
from hapticloud.core.geometry.primitives import Sphere
from hapticloud.core.perception import PerceptionConfig, SurfaceEstimate
from hapticloud.core.recording import RecordConfig, primitive_to_dict, storage_roi
from numpy.typing import NDArray

from .recorder import config_tomls
from .writer import RecordingWriter

R_HIP_M = 0.04
CAMERAS = (("front", (0.7, 0.15, 0.35)), ("side", (0.55, -0.35, 0.4)))


@dataclass(frozen=True)
class SynthTimes:
    """When the synthetic session holds, stops and faults (s, intervals ``[t0, t1)``)."""

    hold: tuple[float, float] = (1.0, 1.3)
    stop: tuple[float, float] = (2.0, 2.2)
    fault: tuple[float, float] = (2.5, 2.8)


def _look_at(origin: NDArray, target: NDArray) -> NDArray[np.float64]:
    """``pose_world_camera`` of a camera at ``origin`` looking at ``target`` (optical z
    forward, y down as the world's -z)."""
    z = target - origin
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, origin
    return pose


def gap_m(t: float, period_s: float) -> float:
    """The HIP's free distance to the wall at ``t`` (1 mm to 100 mm)."""
    return 0.001 + 0.099 * 0.5 * (1.0 + math.cos(2.0 * math.pi * t / period_s))


def _wall_depth(k: CameraIntrinsics, pose: NDArray, roi: Sequence[int]) -> NDArray[np.float32]:
    """Depth (m) of the wall ``x = 0`` in the pixels of ``roi`` (0 where it is not in view)."""
    r0, r1, c0, c1 = roi
    xs, ys = k.pixel_rays()
    rx, ry = xs[r0:r1, c0:c1].astype(np.float64), ys[r0:r1, c0:c1].astype(np.float64)
    rot, origin = pose[:3, :3], pose[:3, 3]
    dx = rot[0, 0] * rx + rot[0, 1] * ry + rot[0, 2]  # world x of the ray with camera z = 1
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(dx < -1e-9, -origin[0] / dx, 0.0)
    return depth.astype(np.float32)


def synthesize(
    path: str | Path,
    duration_s: float = 3.0,
    *,
    rate_hz: float = 30.0,
    period_s: float = 2.0,
    times: SynthTimes | None = None,
    width: int = 424,
    height: int = 240,
    camera_stops_s: Mapping[str, float] | None = None,
) -> Path:
    """Write the synthetic recording (see the module docstring) to ``path``; returns it.
    ``camera_stops_s``: cameras that deliver no frame after that time (s)."""
    stops = dict(camera_stops_s or {})
    times = times or SynthTimes()
    perception = PerceptionConfig()
    record = RecordConfig()
    from hapticloud.core.fusion import FusionConfig

    clock = [0.0]
    path = Path(path)
    stream = open(path, "wb")
    writer = RecordingWriter(
        stream,
        {"source": "synthetic", "clock": "scene", "scene": "wall"},
        config_tomls(perception, FusionConfig()),
        None,
        record,
        clock=lambda: clock[0],
    )
    k = CameraIntrinsics.d435(width, height)
    target = np.array([0.0, 0.0, 0.3])
    poses = [_look_at(np.array(o, dtype=np.float64), target) for _, o in CAMERAS]
    n_cams = len(CAMERAS)
    frame_dt = 1.0 / rate_hz
    control_dt = 0.01
    from ..control.messages import estimate_to_dict

    events = [
        (times.hold[0], "warning", "space", "holding: no fresh surface"),
        (times.hold[1], "info", "space", "known: fresh surface"),
        (times.stop[0], "warning", "space", "stopped: no surface for too long"),
        (times.stop[1], "info", "space", "known: fresh surface"),
        (times.fault[0], "error", "state", "fault: synthetic drive fault"),
        (times.fault[1], "info", "state", "enabled: reset"),
    ]
    seq = 0
    next_control = 0.0
    n_frames = math.floor(duration_s * rate_hz) + 1
    ev = 0
    for i in range(n_frames):
        for j, (name, _origin) in enumerate(CAMERAS):
            t = i * frame_dt + j * frame_dt / n_cams
            if t > duration_s:
                break
            while next_control <= t:
                _control(writer, next_control, period_s, times)
                next_control = round(next_control + control_dt, 9)
            while ev < len(events) and events[ev][0] <= t:
                et, level, source, text = events[ev]
                if et <= duration_s:
                    writer.event(et, level, source, text)
                ev += 1
            clock[0] = t
            if t > stops.get(name, math.inf):
                continue
            hip = np.array([R_HIP_M + gap_m(t, period_s), 0.0, 0.3])
            full = DepthFrame(
                t,
                name,
                np.broadcast_to(np.float32(0.0), (height, width)),
                k,
                poses[j],
            )
            roi = storage_roi(full, hip, perception.crop, record)
            pixels = _wall_depth(k, poses[j], roi)
            seq += 1
            blind = times.stop[0] <= t < times.stop[1]
            est = SurfaceEstimate(
                t=t,
                camera=name,
                centroid=np.array([0.0, hip[1], hip[2]]),
                normal=np.array([1.0, 0.0, 0.0]),
                valid=not blind,
                reason="synthetic blind spell" if blind else "",
                hip=hip,
                seq=seq,
            )
            shapes = [primitive_to_dict(Sphere(hip, 0.02))]
            writer.capture(t, full, roi, pixels, hip.tolist(), shapes, seq)
            writer.estimate(t, name, estimate_to_dict(est))
            writer.maybe_flush()
    writer.close()
    return path


def _control(writer: RecordingWriter, t: float, period_s: float, times: SynthTimes) -> None:
    gap = gap_m(t, period_s)
    hip = [R_HIP_M + gap, 0.0, 0.3]
    if times.stop[0] <= t < times.stop[1]:
        space = "stopped"
    elif times.hold[0] <= t < times.hold[1]:
        space = "holding"
    else:
        space = "known"
    state = "fault" if times.fault[0] <= t < times.fault[1] else "enabled"
    writer.control_state(
        t,
        {
            "t": t,
            "hip": hip,
            "q": [0.0] * 6,
            "tau": [0.0] * 6,
            "d_proj_m": gap,
            "fused_valid": space == "known",
            "fused_centroid": [0.0, 0.0, 0.3],
            "fused_normal": [1.0, 0.0, 0.0],
            "true_margin_m": gap,
            "state": state,
            "space": space,
            "tick_us": 300.0,
            "misses": 0,
        },
        R_HIP_M,
    )


__all__ = ["CAMERAS", "R_HIP_M", "SynthTimes", "gap_m", "synthesize"]
