"""Writes a recording (:mod:`.format`) to an MCAP file, crash-safe to within one flush period.

:class:`RecordingWriter` encodes each message (:mod:`.format`), appends it to the open zstd chunk
and, at most :attr:`~hapticloud.core.recording.RecordConfig.flush_period_s` after the oldest
message of that chunk, closes the chunk (its message index follows it) and flushes the file: a
process killed at any moment leaves a file whose whole chunks hold every message older than that
period, which :class:`~.reader.Recording` reads and :func:`~.recover.recover` re-indexes.
:meth:`RecordingWriter.close` writes the summary (channels, statistics, chunk index), after
which the file opens by its index alone.

It runs wherever it is called: the recorder process (:mod:`.recorder`) calls it, off the control
loop and at low priority.
"""

from __future__ import annotations

import errno
import io
import time
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from typing import IO, Any

import numpy as np
from hapticloud.core.camera import DepthFrame
from hapticloud.core.recording import RecordConfig
from mcap.writer import CompressionType, Writer
from numpy.typing import NDArray

from . import format as fmt

#: A chunk is closed at this size even before the flush period: it bounds the reader's memory
#: and what a full disk or a kill loses when a run writes faster than real time.
CHUNK_BYTES = 1024 * 1024


class LimitedFile(io.RawIOBase):
    """A file that fails as a full disk does (``OSError(ENOSPC)``) once ``limit_bytes`` would be
    exceeded: a quota, and the disk-full tests' stand-in. The bytes before the limit are written."""

    def __init__(self, path: str, limit_bytes: int) -> None:
        self._file = open(path, "wb")
        self._limit = int(limit_bytes)
        self._written = 0

    def writable(self) -> bool:
        return True

    def write(self, data: Any) -> int:
        view = memoryview(data).cast("B")
        room = self._limit - self._written
        if len(view) > room:
            if room > 0:
                self._file.write(view[:room])
                self._written += room
            self._file.flush()
            raise OSError(errno.ENOSPC, "No space left on device")
        self._file.write(view)
        self._written += len(view)
        return len(view)

    def tell(self) -> int:
        return self._written

    def flush(self) -> None:
        if not self._file.closed:
            self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()
        super().close()


class RecordingWriter:
    """One recording file (see the module docstring).

    Parameters
    ----------
    stream
        A binary file opened for writing (the writer closes it).
    metadata
        The ``hapticloud`` metadata record's extra keys (``source``, ``clock``, ...).
    config_toml
        ``{"perception": ..., "fusion": ..., "record": ...}`` TOML texts.
    scene
        ``{"name": ..., "toml": ...}`` or ``None``.
    record
        Flush period and what frames store.
    clock
        Seconds for the flush timer (a test can drive it).
    """

    def __init__(
        self,
        stream: IO[bytes],
        metadata: Mapping[str, str],
        config_toml: Mapping[str, str],
        scene: Mapping[str, str] | None = None,
        record: RecordConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        _version = software_version()
        self.config = record or RecordConfig()
        self._stream = stream
        self._clock = clock
        self._mcap = Writer(stream, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._mcap.start(profile="", library=f"hapticloud {_version}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._poses: dict[str, bytes] = {}
        self._chunk_opened: float | None = None
        self.messages = 0
        self.closed = False
        info = {
            "format_version": str(fmt.FORMAT_VERSION),
            "software": f"hapticloud {_version}",
            "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "frames": self.config.frames,
            "depth_encoding": fmt.DEPTH_ENCODING,
            **{k: str(v) for k, v in metadata.items()},
        }
        self._mcap.add_metadata(fmt.METADATA_NAME, info)
        self._mcap.add_metadata(fmt.CONFIG_METADATA, dict(config_toml))
        if scene is not None:
            self._mcap.add_metadata(fmt.SCENE_METADATA, dict(scene))
        # The header and metadata reach the file at once: even a file killed in its first
        # second says what it is.
        self._mcap.flush()

    # ----- channels ------------------------------------------------------------------------------
    def _channel(self, topic: str, kind: str) -> int:
        channel = self._channels.get(topic)
        if channel is not None:
            return channel
        if kind in fmt.FOXGLOVE_KINDS:
            name, encoding, data = fmt.foxglove_schema(fmt.FOXGLOVE_KINDS[kind])
            message_encoding = "protobuf"
        else:
            name, encoding = fmt.JSON_KINDS[kind], "jsonschema"
            data, message_encoding = fmt.json_schema_bytes(name), "json"
        schema = self._schemas.get(name)
        if schema is None:
            schema = self._schemas[name] = self._mcap.register_schema(name, encoding, data)
        channel = self._mcap.register_channel(topic, message_encoding, schema)
        self._channels[topic] = channel
        return channel

    def _add(self, topic: str, kind: str, log_time_ns: int, data: bytes) -> None:
        channel = self._channel(topic, kind)
        self._mcap.add_message(channel, log_time_ns, data, log_time_ns)
        self.messages += 1
        if self._chunk_opened is None:
            self._chunk_opened = self._clock()
        self.maybe_flush()

    def maybe_flush(self) -> bool:
        """Close the chunk and flush the file if its oldest message waited a flush period."""
        opened = self._chunk_opened
        if opened is None or self._clock() - opened < self.config.flush_period_s:
            return False
        self.flush()
        return True

    def flush(self) -> None:
        """Close the open chunk and flush it to the file (what a crash then keeps)."""
        self._mcap.flush()
        self._chunk_opened = None

    @property
    def bytes_written(self) -> int:
        return int(self._stream.tell())

    # ----- messages ------------------------------------------------------------------------------
    def capture(
        self,
        log_time_s: float,
        frame: DepthFrame,
        roi: Sequence[int],
        pixels: NDArray[np.float32],
        hip: Sequence[float],
        exclude: Sequence[Mapping[str, Any]],
        seq: int,
    ) -> None:
        """One camera frame: the stored rectangle's pixels, its calibration, the capture record
        and (when the camera moved or is new) its transform. ``frame.depth_m`` is not read:
        ``pixels`` are the rectangle ``roi`` of it (the caller sends only those)."""
        cam = frame.camera
        ns = fmt.to_ns(log_time_s)
        pose_key = np.asarray(frame.pose_world_camera, dtype=np.float64).tobytes()
        if self._poses.get(cam) != pose_key:
            self._poses[cam] = pose_key
            self._add(
                fmt.TF_TOPIC, "tf", ns, fmt.encode_transform(ns, cam, frame.pose_world_camera)
            )
        self._add(fmt.depth_topic(cam), "depth", ns, fmt.encode_depth(ns, cam, pixels))
        self._add(
            fmt.cloud_topic(cam),
            "cloud",
            ns,
            fmt.encode_cloud(ns, cam, pixels, frame.intrinsics, roi),
        )
        self._add(
            fmt.calibration_topic(cam),
            "calibration",
            ns,
            fmt.encode_calibration(ns, cam, frame.intrinsics, roi),
        )
        record = fmt.capture_to_dict(
            frame.t, cam, seq, roi, frame.intrinsics, frame.pose_world_camera, hip, exclude
        )
        self._add(fmt.capture_topic(cam), "capture", ns, fmt.encode_json(record))

    def estimate(self, log_time_s: float, camera: str, wire: Mapping[str, Any]) -> None:
        """One estimate as :func:`~hapticloud.hardware.control.messages.estimate_to_dict`."""
        ns = fmt.to_ns(log_time_s)
        self._add(fmt.estimate_topic(camera), "estimate", ns, fmt.encode_json(wire))

    def control_state(
        self, log_time_s: float, state: Mapping[str, Any], hip_radius_m: float
    ) -> None:
        """The tick's view (``CONTROL_SCHEMA``) and its 3D markers."""
        ns = fmt.to_ns(log_time_s)
        self._add(fmt.CONTROL_TOPIC, "control", ns, fmt.encode_json(state))
        valid = bool(state.get("fused_valid"))
        self._add(
            fmt.SURFACE_TOPIC,
            "surface",
            ns,
            fmt.encode_surface(
                ns,
                state["hip"],
                hip_radius_m,
                state.get("fused_centroid") if valid else None,
                state.get("fused_normal") if valid else None,
            ),
        )

    def event(self, log_time_s: float, level: str, source: str, text: str) -> None:
        ns = fmt.to_ns(log_time_s)
        self._add(fmt.EVENTS_TOPIC, "events", ns, fmt.encode_log(ns, level, source, text))

    def close(self) -> None:
        """Write the summary and the footer: the file is complete and indexed."""
        if self.closed:
            return
        self.closed = True
        self._mcap.finish()
        self._stream.close()

    def abandon(self) -> None:
        """Stop without the summary (after a write failed): the file keeps its whole chunks."""
        self.closed = True
        try:
            self._stream.close()  # a buffered stream tries its last bytes once more: may fail
        except (OSError, ValueError):
            pass


def software_version() -> str:
    """hapticloud's installed version (``unknown`` when run from an uninstalled tree)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hapticloud")
    except PackageNotFoundError:
        return "unknown"


def open_recording_file(path: str, limit_bytes: int | None = None) -> IO[bytes]:
    """The file a recording is written to (``limit_bytes``: a quota, see :class:`LimitedFile`)."""
    if limit_bytes is None:
        return open(path, "wb")
    return io.BufferedWriter(LimitedFile(path, limit_bytes))


__all__ = [
    "CHUNK_BYTES",
    "LimitedFile",
    "RecordingWriter",
    "open_recording_file",
    "software_version",
]
