"""``hapticloud import BAG OUT.mcap``: depth images of a ROS bag as a recording replay can re-run.

Reads a ROS 1 bag (``.bag``) or a ROS 2 bag (a folder with ``metadata.yaml``, or its ``.db3`` or
``.mcap`` file) with :mod:`rosbags`. Every ``sensor_msgs/Image`` topic of a depth encoding
(``16UC1`` millimetres, ``32FC1`` metres) becomes a camera, paired with the
``sensor_msgs/CameraInfo`` of its namespace (``.../image_raw`` with ``.../camera_info``); each
image is stored whole (``frames = "full"``) with the latest intrinsics seen before it.

A bag does not know the robot: the HIP (``hip_m``, fixed, in the camera's frame) comes from the
command line, the camera's pose is the identity (its optical frame is the world) and no robot
shape is excluded. The imported recording has frames and no estimates: ``hapticloud replay``
estimates on it and reports what it found.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from hapticloud.core.camera import CameraIntrinsics, DepthFrame
from hapticloud.core.errors import RecordingError
from hapticloud.core.recording import RecordConfig

from .recorder import config_tomls
from .writer import RecordingWriter

DEPTH_ENCODINGS = {"16UC1": ("<u2", 1e-3), "mono16": ("<u2", 1e-3), "32FC1": ("<f4", 1.0)}


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0] if "/" in topic.strip("/") else topic


def _camera_name(topic: str) -> str:
    parts = [p for p in _namespace(topic).split("/") if p]
    return "_".join(parts) or "camera"


def _depth(msg: Any) -> np.ndarray:
    dtype, scale = DEPTH_ENCODINGS[msg.encoding]
    item = np.dtype(dtype).itemsize
    if msg.is_bigendian:
        dtype = dtype.replace("<", ">")
    rows = np.frombuffer(bytes(msg.data), dtype=dtype, count=msg.height * msg.step // item)
    img = rows.reshape(msg.height, msg.step // item)[:, : msg.width].astype(np.float32)
    return img * np.float32(scale) if scale != 1.0 else img


def import_bag(
    bag: str | os.PathLike[str],
    out: str | os.PathLike[str],
    hip_m: Sequence[float],
    *,
    perception: Any = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Convert ``bag`` into the recording ``out``; returns ``{"cameras": {name: frames},
    "skipped": {topic: why}, "messages"}``.

    Raises
    ------
    RecordingError
        The bag cannot be read, or has no depth image with its camera info.
    """
    from hapticloud.core.fusion import FusionConfig
    from hapticloud.core.perception import PerceptionConfig
    from rosbags.highlevel import AnyReader, AnyReaderError

    say = progress or (lambda _text: None)
    path = Path(bag)
    if not path.exists():
        raise RecordingError(f"{bag}: no such file or folder")
    if (
        path.suffix in (".db3", ".mcap")
        and path.is_file()
        and (path.parent / "metadata.yaml").exists()
    ):
        path = path.parent  # a ROS 2 bag is its folder
    hip = [float(x) for x in hip_m]
    if len(hip) != 3 or not all(np.isfinite(hip)):
        raise RecordingError(f"--hip {hip_m}: expected three finite numbers (m)")
    record = RecordConfig(frames="full")
    cameras: dict[str, int] = {}
    skipped: dict[str, str] = {}
    try:
        reader = AnyReader([path])
        reader.open()
    except (AnyReaderError, OSError, ValueError) as err:
        raise RecordingError(f"{bag}: not a readable ROS bag ({err})") from None
    try:
        images = [c for c in reader.connections if c.msgtype == "sensor_msgs/msg/Image"]
        infos = {
            _namespace(c.topic): c
            for c in reader.connections
            if c.msgtype == "sensor_msgs/msg/CameraInfo"
        }
        if not images:
            raise RecordingError(f"{bag}: no sensor_msgs/Image topic")
        wanted = [c for c in images if _namespace(c.topic) in infos]
        for c in images:
            if c not in wanted:
                skipped[c.topic] = "no camera_info in its namespace"
        if not wanted:
            raise RecordingError(f"{bag}: no depth image topic with a camera_info beside it")
        pcfg = perception or PerceptionConfig()
        stream = open(out, "wb")
        writer = RecordingWriter(
            stream,
            {"source": f"import {path.name}", "clock": "bag", "hip_m": str(hip)},
            {**config_tomls(pcfg, FusionConfig())},
            None,
            record,
        )
        latest: dict[str, CameraIntrinsics] = {}
        conns = wanted + [infos[_namespace(c.topic)] for c in wanted]
        for conn, t_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            ns = _namespace(conn.topic)
            if conn.msgtype == "sensor_msgs/msg/CameraInfo":
                # ROS 1 spells it K, ROS 2 k.
                k = [float(x) for x in (msg.k if hasattr(msg, "k") else msg.K)]
                if k[0] > 0 and k[4] > 0:
                    latest[ns] = CameraIntrinsics(
                        int(msg.width), int(msg.height), k[0], k[4], k[2], k[5]
                    )
                continue
            if msg.encoding not in DEPTH_ENCODINGS:
                skipped[conn.topic] = f"encoding {msg.encoding} is not depth"
                continue
            intr = latest.get(ns)
            if intr is None or (intr.width, intr.height) != (msg.width, msg.height):
                continue  # no intrinsics for this image yet
            name = _camera_name(conn.topic)
            depth = _depth(msg)
            t = t_ns / 1e9
            frame = DepthFrame(t, name, depth, intr)
            seq = cameras.get(name, 0) + 1
            cameras[name] = seq
            writer.capture(t, frame, (0, intr.height, 0, intr.width), depth, hip, [], seq)
        writer.close()
    finally:
        reader.close()
    if not cameras:
        raise RecordingError(f"{bag}: no depth image had camera_info before it")
    say(f"imported {sum(cameras.values())} frames of {len(cameras)} cameras")
    return {"cameras": cameras, "skipped": skipped, "messages": writer.messages}


__all__ = ["DEPTH_ENCODINGS", "import_bag"]
