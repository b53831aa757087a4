"""The recording format, in one place: channels, schemas, the encoding of every message, metadata.

A recording is an MCAP file (zstd-compressed chunks, indexed when finished). Its channels use
the Foxglove schemas where one fits, so Foxglove opens it (protobuf encoding), and JSON with a
JSON Schema for what is ours:

======================================  ===========================  ========  =================
topic                                   schema                       encoding  frame
======================================  ===========================  ========  =================
``/camera/<name>/depth``                ``foxglove.RawImage``        protobuf  ``<name>``
``/camera/<name>/calibration``          ``foxglove.CameraCalibration``  protobuf  ``<name>``
``/camera/<name>/capture``              ``hapticloud.Capture``       json      world
``/camera/<name>/cloud``                ``foxglove.PointCloud``      protobuf  ``<name>``
``/tf``                                 ``foxglove.FrameTransforms`` protobuf  world -> ``<name>``
``/perception/<name>/estimate``         ``hapticloud.SurfaceEstimate``  json   world
``/control/state``                      ``hapticloud.ControlState``  json      world
``/scene/surface``                      ``foxglove.SceneUpdate``     protobuf  world
``/events``                             ``foxglove.Log``             protobuf  -
======================================  ===========================  ========  =================

- depth: the stored rectangle (``roi`` of the capture; the whole image for ``frames = "full"``)
  as ``32FC1``, metres, little-endian, 0 = no depth: lossless for the float32 frames the
  pipeline reads, so a re-run reproduces the recorded estimates exactly;
- calibration: the pin-hole model of that rectangle (principal point shifted by its corner), so
  Foxglove deprojects it in place;
- cloud: the stored rectangle's valid pixels as points in the camera's frame (every
  :data:`CLOUD_STRIDE`-th pixel each way, float32 x, y, z in metres): what Foxglove's 3D panel
  draws of the frame (a re-run reads the depth channel, not this);
- capture: what the pipeline needs besides the pixels: the frame's time ``t`` (the pipeline's
  clock), the full image's intrinsics, ``pose_world_camera`` (4x4, row-major), the rectangle
  ``roi = [row0, row1, col0, col1]``, the HIP at capture and the robot's exclusion shapes, and
  ``seq``, the sequence number of the estimate recorded for this frame;
- estimate: :func:`hapticloud.hardware.control.messages.estimate_to_dict`, the fields of the
  control process's estimate wire form (one encoding for the pipe and the file);
- control state: the tick's view, every tick of a deterministic run (800 Hz) and every 8th of
  a real-time session's (the snapshots, 100 Hz): HIP, joint positions and torques,
  ``d_proj``, the fused surface, session state and space state;
- surface: spheres for the HIP and the fused centroid, an arrow for its normal (Foxglove 3D);
- events: session transitions, faults, the recorder's own alarms.

Log times are nanoseconds on the recording's clock (metadata ``clock``: ``scene`` seconds from
the run's start, or ``monotonic`` for real-time sessions). Metadata record ``hapticloud`` holds
``format_version`` (:data:`FORMAT_VERSION`; a reader refuses a newer one), ``software``,
``source``, ``clock``, ``created_utc``, ``frames``; record ``hapticloud.config`` the TOML of the
``perception``, ``fusion`` and ``record`` parameters; record ``hapticloud.scene`` the scene's
``name`` and ``toml`` when the run had a scene.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import foxglove.messages as fm
import numpy as np
from hapticloud.core.camera import CameraIntrinsics
from numpy.typing import NDArray

FORMAT_VERSION = 1
METADATA_NAME = "hapticloud"
CONFIG_METADATA = "hapticloud.config"
SCENE_METADATA = "hapticloud.scene"
DEPTH_ENCODING = "32FC1"

TF_TOPIC = "/tf"
CONTROL_TOPIC = "/control/state"
SURFACE_TOPIC = "/scene/surface"
EVENTS_TOPIC = "/events"
WORLD_FRAME = "world"

CAPTURE_SCHEMA = "hapticloud.Capture"
ESTIMATE_SCHEMA = "hapticloud.SurfaceEstimate"
CONTROL_SCHEMA = "hapticloud.ControlState"


def depth_topic(camera: str) -> str:
    return f"/camera/{camera}/depth"


#: Every n-th pixel of the stored rectangle (both ways) goes into the cloud channel.
CLOUD_STRIDE = 4


def cloud_topic(camera: str) -> str:
    return f"/camera/{camera}/cloud"


def calibration_topic(camera: str) -> str:
    return f"/camera/{camera}/calibration"


def capture_topic(camera: str) -> str:
    return f"/camera/{camera}/capture"


def estimate_topic(camera: str) -> str:
    return f"/perception/{camera}/estimate"


def camera_of(topic: str) -> str | None:
    """The camera a per-camera topic belongs to (``None`` for the others)."""
    parts = topic.split("/")
    if len(parts) == 4 and parts[1] in ("camera", "perception"):
        return parts[2]
    return None


def _number_array(n: int | None = None) -> dict[str, Any]:
    schema: dict[str, Any] = {"type": "array", "items": {"type": "number"}}
    if n is not None:
        schema.update(minItems=n, maxItems=n)
    return schema


#: JSON Schemas of our JSON channels (what Foxglove shows; the reader checks the keys it needs).
JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    CAPTURE_SCHEMA: {
        "title": CAPTURE_SCHEMA,
        "description": "What the perception pipeline needs besides a frame's pixels",
        "type": "object",
        "properties": {
            "t": {"type": "number", "description": "frame time the pipeline saw (s)"},
            "camera": {"type": "string"},
            "seq": {"type": "integer", "description": "seq of the estimate recorded for it"},
            "roi": {"type": "array", "items": {"type": "integer"}, "minItems": 4, "maxItems": 4},
            "width": {"type": "integer"},
            "height": {"type": "integer"},
            "fx": {"type": "number"},
            "fy": {"type": "number"},
            "cx": {"type": "number"},
            "cy": {"type": "number"},
            "pose_world_camera": _number_array(16),
            "hip": _number_array(3),
            "exclude": {"type": "array", "items": {"type": "object"}},
        },
        "required": [
            "t",
            "camera",
            "seq",
            "roi",
            "width",
            "height",
            "fx",
            "fy",
            "cx",
            "cy",
            "pose_world_camera",
            "hip",
            "exclude",
        ],
    },
    ESTIMATE_SCHEMA: {
        "title": ESTIMATE_SCHEMA,
        "description": "One camera's surface estimate (the control process's wire form, named)",
        "type": "object",
        "properties": {
            "t": {"type": "number"},
            "camera": {"type": "string"},
            "centroid": _number_array(3),
            "normal": _number_array(3),
            "valid": {"type": "boolean"},
            "quality": {"type": "number"},
            "reason": {"type": "string"},
            "method": {"type": "string"},
            "seq": {"type": "integer"},
            "free_m": {"type": "number"},
            "hip": {"anyOf": [_number_array(3), {"type": "null"}]},
            "residual_m": {
                "type": "number",
                "description": "the surface fit's noise (m); 0 or absent: unknown",
            },
        },
    },
    CONTROL_SCHEMA: {
        "title": CONTROL_SCHEMA,
        "description": "The control tick's view (every 8th tick)",
        "type": "object",
        "properties": {
            "t": {"type": "number"},
            "hip": _number_array(3),
            "q": _number_array(),
            "tau": _number_array(),
            "d_proj_m": {"type": "number"},
            "fused_valid": {"type": "boolean"},
            "fused_centroid": _number_array(3),
            "fused_normal": _number_array(3),
            "state": {"type": "string"},
            "space": {"type": "string"},
        },
    },
}


def json_schema_bytes(name: str) -> bytes:
    return json.dumps(JSON_SCHEMAS[name]).encode()


def encode_json(data: Mapping[str, Any]) -> bytes:
    """JSON without NaN/inf (not JSON): they become ``null``."""
    return json.dumps(_finite(data), separators=(",", ":")).encode()


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def decode_json(data: bytes) -> Any:
    return json.loads(data)


def _stamp(log_time_ns: int) -> fm.Timestamp:
    return fm.Timestamp(sec=log_time_ns // 1_000_000_000, nsec=log_time_ns % 1_000_000_000)


def to_ns(seconds: float) -> int:
    """A recording time (s) as MCAP log time (ns, never negative)."""
    return max(0, round(seconds * 1e9))


# ----- foxglove messages --------------------------------------------------------------------------
def encode_depth(log_time_ns: int, camera: str, pixels: NDArray[np.float32]) -> bytes:
    """``foxglove.RawImage`` 32FC1 of a depth rectangle (metres)."""
    px = np.ascontiguousarray(pixels, dtype="<f4")
    h, w = px.shape
    return fm.RawImage(
        timestamp=_stamp(log_time_ns),
        frame_id=camera,
        width=w,
        height=h,
        encoding=DEPTH_ENCODING,
        step=4 * w,
        data=px.tobytes(),
    ).encode()


def encode_cloud(
    log_time_ns: int,
    camera: str,
    pixels: NDArray[np.float32],
    k: CameraIntrinsics,
    roi: Sequence[int],
) -> bytes:
    """``foxglove.PointCloud`` of a depth rectangle's valid pixels, in the camera's frame."""
    row0, _, col0, _ = (int(v) for v in roi)
    z = pixels[::CLOUD_STRIDE, ::CLOUD_STRIDE]
    rows, cols = np.nonzero(z > 0.0)
    depth = z[rows, cols].astype(np.float32)
    u = (col0 + CLOUD_STRIDE * cols).astype(np.float32)
    v = (row0 + CLOUD_STRIDE * rows).astype(np.float32)
    xyz = np.empty((depth.size, 3), dtype=np.float32)
    xyz[:, 0] = (u - np.float32(k.cx)) / np.float32(k.fx) * depth
    xyz[:, 1] = (v - np.float32(k.cy)) / np.float32(k.fy) * depth
    xyz[:, 2] = depth
    numeric = fm.PackedElementFieldNumericType.Float32
    return fm.PointCloud(
        timestamp=_stamp(log_time_ns),
        frame_id=camera,
        pose=_pose((0.0, 0.0, 0.0)),
        point_stride=12,
        fields=[
            fm.PackedElementField(name=n, offset=4 * i, type=numeric) for i, n in enumerate("xyz")
        ],
        data=xyz.tobytes(),
    ).encode()


def decode_depth(msg: Any) -> NDArray[np.float32]:
    """The pixels of a decoded ``foxglove.RawImage`` (32FC1 or 16UC1 millimetres) in metres."""
    w, h, step = int(msg.width), int(msg.height), int(msg.step)
    if msg.encoding == DEPTH_ENCODING:
        rows = np.frombuffer(msg.data, dtype="<f4", count=h * step // 4).reshape(h, step // 4)
        return np.ascontiguousarray(rows[:, :w], dtype=np.float32)
    if msg.encoding == "16UC1":
        rows = np.frombuffer(msg.data, dtype="<u2", count=h * step // 2).reshape(h, step // 2)
        return (rows[:, :w].astype(np.float32)) * np.float32(0.001)
    raise ValueError(f"depth encoding {msg.encoding!r} (expected {DEPTH_ENCODING} or 16UC1)")


def encode_calibration(
    log_time_ns: int, camera: str, k: CameraIntrinsics, roi: Sequence[int]
) -> bytes:
    """``foxglove.CameraCalibration`` of the stored rectangle (principal point shifted)."""
    r0, r1, c0, c1 = roi
    cx, cy = k.cx - c0, k.cy - r0
    return fm.CameraCalibration(
        timestamp=_stamp(log_time_ns),
        frame_id=camera,
        width=int(c1 - c0),
        height=int(r1 - r0),
        distortion_model="plumb_bob",
        D=[0.0] * 5,
        K=[k.fx, 0.0, cx, 0.0, k.fy, cy, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[k.fx, 0.0, cx, 0.0, 0.0, k.fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    ).encode()


def _quaternion(rot: NDArray[np.float64]) -> fm.Quaternion:
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method: no division by ~0)."""
    m = rot
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = (
            0.25 * s,
            (m[2, 1] - m[1, 2]) / s,
            (m[0, 2] - m[2, 0]) / s,
            (m[1, 0] - m[0, 1]) / s,
        )
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        w, x, y, z = (
            (m[2, 1] - m[1, 2]) / s,
            0.25 * s,
            (m[0, 1] + m[1, 0]) / s,
            (m[0, 2] + m[2, 0]) / s,
        )
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        w, x, y, z = (
            (m[0, 2] - m[2, 0]) / s,
            (m[0, 1] + m[1, 0]) / s,
            0.25 * s,
            (m[1, 2] + m[2, 1]) / s,
        )
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        w, x, y, z = (
            (m[1, 0] - m[0, 1]) / s,
            (m[0, 2] + m[2, 0]) / s,
            (m[1, 2] + m[2, 1]) / s,
            0.25 * s,
        )
    return fm.Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))


def encode_transform(log_time_ns: int, camera: str, pose_world_camera: NDArray) -> bytes:
    """``foxglove.FrameTransforms``: the camera's frame in the world frame."""
    pose = np.asarray(pose_world_camera, dtype=np.float64)
    t = pose[:3, 3]
    return fm.FrameTransforms(
        transforms=[
            fm.FrameTransform(
                timestamp=_stamp(log_time_ns),
                parent_frame_id=WORLD_FRAME,
                child_frame_id=camera,
                translation=fm.Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                rotation=_quaternion(pose[:3, :3]),
            )
        ]
    ).encode()


def _point(p: Sequence[float]) -> fm.Vector3:
    return fm.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _pose(p: Sequence[float], rot: fm.Quaternion | None = None) -> fm.Pose:
    return fm.Pose(position=_point(p), orientation=rot or fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def _arrow_rotation(direction: Sequence[float]) -> fm.Quaternion:
    """The rotation taking +x (a Foxglove arrow's axis) to ``direction``."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / (np.linalg.norm(d) or 1.0)
    x = np.array([1.0, 0.0, 0.0])
    axis = np.cross(x, d)
    s, c = float(np.linalg.norm(axis)), float(x @ d)
    if s < 1e-12:
        return fm.Quaternion(x=0.0, y=0.0, z=1.0 if c < 0 else 0.0, w=0.0 if c < 0 else 1.0)
    axis /= s
    half = math.atan2(s, c) / 2.0
    return fm.Quaternion(
        x=float(axis[0] * math.sin(half)),
        y=float(axis[1] * math.sin(half)),
        z=float(axis[2] * math.sin(half)),
        w=math.cos(half),
    )


def encode_surface(
    log_time_ns: int,
    hip: Sequence[float],
    hip_radius_m: float,
    centroid: Sequence[float] | None,
    normal: Sequence[float] | None,
) -> bytes:
    """``foxglove.SceneUpdate``: the HIP sphere, the fused centroid and its normal (3D panel)."""
    stamp = _stamp(log_time_ns)
    hip_entity = fm.SceneEntity(
        timestamp=stamp,
        frame_id=WORLD_FRAME,
        id="hip",
        spheres=[
            fm.SpherePrimitive(
                pose=_pose(hip),
                size=fm.Vector3(x=2 * hip_radius_m, y=2 * hip_radius_m, z=2 * hip_radius_m),
                color=fm.Color(r=0.2, g=0.5, b=1.0, a=0.4),
            )
        ],
    )
    entities = [hip_entity]
    if centroid is not None and normal is not None:
        entities.append(
            fm.SceneEntity(
                timestamp=stamp,
                frame_id=WORLD_FRAME,
                id="surface",
                spheres=[
                    fm.SpherePrimitive(
                        pose=_pose(centroid),
                        size=fm.Vector3(x=0.01, y=0.01, z=0.01),
                        color=fm.Color(r=1.0, g=0.4, b=0.1, a=1.0),
                    )
                ],
                arrows=[
                    fm.ArrowPrimitive(
                        pose=_pose(centroid, _arrow_rotation(normal)),
                        shaft_length=0.04,
                        shaft_diameter=0.003,
                        head_length=0.01,
                        head_diameter=0.008,
                        color=fm.Color(r=1.0, g=0.4, b=0.1, a=1.0),
                    )
                ],
            )
        )
    return fm.SceneUpdate(entities=entities).encode()


_LEVELS = {"info": fm.LogLevel.Info, "warning": fm.LogLevel.Warning, "error": fm.LogLevel.Error}


def encode_log(log_time_ns: int, level: str, source: str, text: str) -> bytes:
    """``foxglove.Log``: one event line (``level`` info, warning or error; ``source`` names who)."""
    return fm.Log(
        timestamp=_stamp(log_time_ns),
        level=_LEVELS.get(level, fm.LogLevel.Info),
        message=text,
        name=source,
        file="",
        line=0,
    ).encode()


def foxglove_schema(name: str) -> tuple[str, str, bytes]:
    """``(schema name, encoding, data)`` of a Foxglove message class (``RawImage``, ...)."""
    schema = getattr(fm, name).get_schema()
    return schema.name, schema.encoding, bytes(schema.data)


#: topic kind -> (schema name of foxglove.messages or ours, message encoding)
FOXGLOVE_KINDS = {
    "depth": "RawImage",
    "cloud": "PointCloud",
    "calibration": "CameraCalibration",
    "tf": "FrameTransforms",
    "surface": "SceneUpdate",
    "events": "Log",
}
JSON_KINDS = {"capture": CAPTURE_SCHEMA, "estimate": ESTIMATE_SCHEMA, "control": CONTROL_SCHEMA}


def capture_to_dict(
    t: float,
    camera: str,
    seq: int,
    roi: Sequence[int],
    k: CameraIntrinsics,
    pose_world_camera: NDArray,
    hip: Sequence[float],
    exclude: Sequence[Mapping[str, Any]],
) -> dict[str, Any]:
    """The capture channel's message (see the module docstring)."""
    return {
        "t": float(t),
        "camera": camera,
        "seq": int(seq),
        "roi": [int(v) for v in roi],
        "width": k.width,
        "height": k.height,
        "fx": k.fx,
        "fy": k.fy,
        "cx": k.cx,
        "cy": k.cy,
        "pose_world_camera": [float(x) for x in np.asarray(pose_world_camera).reshape(-1)],
        "hip": [float(x) for x in hip],
        "exclude": list(exclude),
    }


__all__ = [
    "CAPTURE_SCHEMA",
    "CONFIG_METADATA",
    "CONTROL_SCHEMA",
    "CONTROL_TOPIC",
    "DEPTH_ENCODING",
    "ESTIMATE_SCHEMA",
    "EVENTS_TOPIC",
    "FORMAT_VERSION",
    "METADATA_NAME",
    "SCENE_METADATA",
    "SURFACE_TOPIC",
    "TF_TOPIC",
    "calibration_topic",
    "camera_of",
    "capture_to_dict",
    "capture_topic",
    "cloud_topic",
    "decode_depth",
    "decode_json",
    "depth_topic",
    "encode_calibration",
    "encode_cloud",
    "encode_depth",
    "encode_json",
    "encode_log",
    "encode_surface",
    "encode_transform",
    "estimate_topic",
    "foxglove_schema",
    "json_schema_bytes",
    "to_ns",
]
