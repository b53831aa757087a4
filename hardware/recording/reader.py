"""Reads a recording: index-only open, seek by time, messages of channels in a time range.

:meth:`Recording.open` reads the summary at the end of a finished file (channels, statistics,
chunk index: no message is read). A file without a summary (the recording process was killed,
the disk filled up) is *unfinished*: it is streamed up to its last whole chunk once, and what
that holds is served the same way; :attr:`Recording.finished` says which, and
:func:`~.recover.recover` rewrites it indexed.

Everything wrong with a file is a :class:`~hapticloud.core.errors.RecordingError` whose one line
names the file and says what (missing, empty, not an MCAP file, not a hapticloud recording, a
newer format version, truncated before its first chunk).

The GUI's timeline uses :meth:`Recording.seek` (the newest message of each channel at a time)
and :meth:`Recording.messages` (a channel's messages in a range); the replay uses
:meth:`Recording.frames` and :meth:`Recording.estimates`.
"""

from __future__ import annotations

import io
import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from hapticloud.core.camera import CameraIntrinsics
from hapticloud.core.errors import RecordingError
from hapticloud.core.recording import CapturedFrame, frame_from_roi, primitive_from_dict
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap_protobuf.decoder import DecoderFactory
from numpy.typing import NDArray

from . import format as fmt

_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class ChannelInfo:
    """One channel: topic, schema name, message encoding, how many messages it has."""

    topic: str
    schema: str
    encoding: str
    messages: int


@dataclass(frozen=True)
class RecordedMessage:
    """One message: its channel, its log time (s, the recording's clock) and its decoded body
    (a dict for JSON channels, the protobuf message for Foxglove ones)."""

    topic: str
    log_time_s: float
    data: Any


@dataclass(frozen=True)
class ChunkSpan:
    """One chunk of the file: its key (for :meth:`Recording.chunk_messages`), the log times of
    its first and last message (ns) and the topics it holds. A cursor that reads small windows
    again and again (a timeline) caches chunks by key instead of decompressing them each time."""

    key: int
    start_ns: int
    end_ns: int
    topics: frozenset[str]


class Recording:
    """An open recording (see the module docstring). Use :meth:`open`; close with :meth:`close`
    or a ``with`` block."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file: io.BufferedReader | None = None
        self._reader: Any = None
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._counts: dict[int, int] = {}
        self._metadata: dict[str, dict[str, str]] = {}
        self._chunks: list[Chunk] = []  # unfinished files only
        self._chunk_channels: list[set[int]] = []  # unfinished files only: channels per chunk
        self._start_ns = 0
        self._end_ns = 0
        self.finished = False
        #: Why an unfinished file ends where it does (``""`` when finished).
        self.truncation = ""
        self._decoders = DecoderFactory()
        self._decoder_cache: dict[int, Any] = {}

    # ----- opening -------------------------------------------------------------------------------
    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> Recording:
        """Open ``path`` by its index (or, unfinished, by streaming it); see the module docstring.

        Raises
        ------
        RecordingError
            One line naming the file and what is wrong with it.
        """
        rec = cls(Path(path))
        where = str(path)
        p = rec.path
        if not p.exists():
            raise RecordingError(f"{where}: no such file")
        if p.is_dir():
            raise RecordingError(f"{where}: is a folder, expected a recording (.mcap)")
        try:
            size = p.stat().st_size
            f = open(p, "rb")
        except OSError as err:
            raise RecordingError(f"{where}: cannot be read ({err.strerror})") from None
        if size == 0:
            f.close()
            raise RecordingError(f"{where}: empty file, not a recording")
        if f.read(len(_MAGIC)) != _MAGIC:
            f.close()
            raise RecordingError(f"{where}: not an MCAP file (no MCAP magic at its start)")
        f.seek(0)
        rec._file = f
        try:
            summary = None
            try:
                reader = make_reader(f, decoder_factories=[rec._decoders])
                summary = reader.get_summary()
            except (McapError, ValueError, EOFError, KeyError, IndexError, OSError):
                summary = None
            if summary is not None and summary.statistics is not None:
                rec._open_indexed(reader, summary)
            else:
                rec._open_streamed()
            rec._check_version()
        except BaseException:
            f.close()
            raise
        return rec

    def _open_indexed(self, reader: Any, summary: Any) -> None:
        self._reader = reader
        self.finished = True
        self._schemas = dict(summary.schemas)
        self._channels = dict(summary.channels)
        stats = summary.statistics
        self._counts = dict(stats.channel_message_counts)
        self._start_ns, self._end_ns = stats.message_start_time, stats.message_end_time
        for meta in reader.iter_metadata():
            self._metadata[meta.name] = dict(meta.metadata)

    def _open_streamed(self) -> None:
        assert self._file is not None
        self._file.seek(0)
        starts, ends = [], []
        try:
            for record in StreamReader(self._file, emit_chunks=True).records:
                if isinstance(record, Schema):
                    self._schemas[record.id] = record
                elif isinstance(record, Channel):
                    self._channels[record.id] = record
                elif isinstance(record, Metadata):
                    self._metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Chunk):
                    self._chunks.append(record)
                    starts.append(record.message_start_time)
                    ends.append(record.message_end_time)
                elif isinstance(record, Message):  # unchunked writers
                    self._chunks.append(_single(record))
                    starts.append(record.log_time)
                    ends.append(record.log_time)
            # A complete file whose summary could not be read still ends in its footer.
            self.truncation = "no summary at its end"
        except Exception as err:  # the torn record at the end of an unfinished file
            self.truncation = f"{type(err).__name__} after the last whole chunk"
        if not self._metadata and not self._chunks:
            raise RecordingError(
                f"{self.path}: truncated before its first chunk ({self.truncation})"
            )
        # Schemas and channels are written inside the chunk that first uses them.
        for chunk in self._chunks:
            records = [chunk._single] if hasattr(chunk, "_single") else breakup_chunk(chunk)
            ids: set[int] = set()
            self._chunk_channels.append(ids)
            for rec in records:
                if isinstance(rec, Message):
                    self._counts[rec.channel_id] = self._counts.get(rec.channel_id, 0) + 1
                    ids.add(rec.channel_id)
                elif isinstance(rec, Schema):
                    self._schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    self._channels[rec.id] = rec
        self._start_ns = min(starts) if starts else 0
        self._end_ns = max(ends) if ends else 0

    def _check_version(self) -> None:
        info = self._metadata.get(fmt.METADATA_NAME)
        if info is None:
            raise RecordingError(
                f"{self.path}: not a hapticloud recording (no '{fmt.METADATA_NAME}' metadata)"
            )
        raw = info.get("format_version", "")
        try:
            version = int(raw)
        except ValueError:
            raise RecordingError(f"{self.path}: format_version {raw!r} is not a number") from None
        if not 1 <= version <= fmt.FORMAT_VERSION:
            raise RecordingError(
                f"{self.path}: recording format version {version} is not supported "
                f"(this hapticloud reads 1 to {fmt.FORMAT_VERSION})"
            )

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----- what it holds -------------------------------------------------------------------------
    @property
    def metadata(self) -> dict[str, dict[str, str]]:
        """Every metadata record by name (``hapticloud``, ``hapticloud.config``, ...)."""
        return {k: dict(v) for k, v in self._metadata.items()}

    @property
    def info(self) -> dict[str, str]:
        return dict(self._metadata.get(fmt.METADATA_NAME, {}))

    @property
    def format_version(self) -> int:
        return int(self.info["format_version"])

    @property
    def start_s(self) -> float:
        return self._start_ns / 1e9

    @property
    def end_s(self) -> float:
        return self._end_ns / 1e9

    @property
    def duration_s(self) -> float:
        return (self._end_ns - self._start_ns) / 1e9

    @property
    def channels(self) -> dict[str, ChannelInfo]:
        out = {}
        for cid, ch in sorted(self._channels.items()):
            schema = self._schemas.get(ch.schema_id)
            out[ch.topic] = ChannelInfo(
                ch.topic,
                schema.name if schema else "",
                ch.message_encoding,
                self._counts.get(cid, 0),
            )
        return out

    @property
    def cameras(self) -> list[str]:
        """Cameras with recorded frames, in the order their channels appear."""
        names: list[str] = []
        for topic in self.channels:
            cam = fmt.camera_of(topic)
            if cam is not None and topic == fmt.capture_topic(cam) and cam not in names:
                names.append(cam)
        return names

    @property
    def message_count(self) -> int:
        return sum(self._counts.values())

    def config_toml(self) -> dict[str, str]:
        """The recorded ``perception``, ``fusion`` and ``record`` parameters (TOML texts)."""
        return dict(self._metadata.get(fmt.CONFIG_METADATA, {}))

    # ----- messages ------------------------------------------------------------------------------
    def _decode(self, channel_id: int, data: bytes) -> Any:
        ch = self._channels[channel_id]
        if ch.message_encoding == "json":
            return fmt.decode_json(data)
        decoder = self._decoder_cache.get(channel_id)
        if decoder is None:
            schema = self._schemas[ch.schema_id]
            decoder = self._decoders.decoder_for(ch.message_encoding, schema)
            if decoder is None:
                raise RecordingError(
                    f"{self.path}: {ch.topic}: cannot decode {ch.message_encoding} messages"
                )
            self._decoder_cache[channel_id] = decoder
        return decoder(data)

    def raw_messages(
        self,
        topics: Iterable[str] | None = None,
        start_s: float | None = None,
        end_s: float | None = None,
    ) -> Iterator[tuple[str, int, bytes]]:
        """``(topic, log time ns, encoded bytes)`` of ``topics`` (all: ``None``) with
        ``start_s <= log time < end_s``, in log-time order."""
        wanted = None if topics is None else set(topics)
        lo = None if start_s is None else fmt.to_ns(start_s)
        hi = None if end_s is None else fmt.to_ns(end_s)
        if self._reader is not None:
            try:
                for _schema, channel, message in self._reader.iter_messages(
                    topics=None if wanted is None else sorted(wanted),
                    starting_at=lo,
                    ending_before=hi,
                    log_time_order=True,
                ):
                    yield channel.topic, message.log_time, message.data
            except (McapError, ValueError, EOFError) as err:
                raise RecordingError(f"{self.path}: unreadable chunk ({err})") from None
            return
        ids = {cid for cid, ch in self._channels.items() if wanted is None or ch.topic in wanted}
        picked: list[Message] = []
        for chunk in self._chunks:
            if lo is not None and chunk.message_end_time < lo:
                continue
            if hi is not None and chunk.message_start_time >= hi:
                continue
            for rec in _messages_of(chunk):
                if rec.channel_id not in ids:
                    continue
                if (lo is not None and rec.log_time < lo) or (
                    hi is not None and rec.log_time >= hi
                ):
                    continue
                picked.append(rec)
        picked.sort(key=lambda m: m.log_time)  # stable: file order within one time
        for rec in picked:
            yield self._channels[rec.channel_id].topic, rec.log_time, rec.data

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_s: float | None = None,
        end_s: float | None = None,
    ) -> Iterator[RecordedMessage]:
        """Decoded messages of ``topics`` in ``[start_s, end_s)``, in log-time order."""
        by_topic = {ch.topic: cid for cid, ch in self._channels.items()}
        for topic, ns, data in self.raw_messages(topics, start_s, end_s):
            yield RecordedMessage(topic, ns / 1e9, self._decode(by_topic[topic], data))

    def chunk_spans(self) -> list[ChunkSpan]:
        """Every chunk of the file (index only: nothing is decompressed), in file order."""
        spans = []
        if self._reader is not None:
            summary = self._reader.get_summary()
            for index in summary.chunk_indexes:
                topics = frozenset(
                    self._channels[cid].topic
                    for cid in index.message_index_offsets
                    if cid in self._channels
                )
                spans.append(
                    ChunkSpan(
                        index.chunk_start_offset,
                        index.message_start_time,
                        index.message_end_time,
                        topics,
                    )
                )
            return spans
        for key, (chunk, ids) in enumerate(zip(self._chunks, self._chunk_channels, strict=True)):
            topics = frozenset(self._channels[cid].topic for cid in ids if cid in self._channels)
            spans.append(ChunkSpan(key, chunk.message_start_time, chunk.message_end_time, topics))
        return spans

    def chunk_messages(self, key: int) -> list[tuple[str, int, bytes]]:
        """``(topic, log time ns, encoded bytes)`` of every message of one chunk
        (:attr:`ChunkSpan.key`), in log-time order (file order within one time)."""
        try:
            if self._reader is not None:
                assert self._file is not None
                from mcap.data_stream import ReadDataStream

                self._file.seek(key + 1 + 8)  # opcode, record length
                chunk = Chunk.read(ReadDataStream(self._file))
            else:
                chunk = self._chunks[key]
            records = _messages_of(chunk)
        except (McapError, ValueError, EOFError, OSError, IndexError) as err:
            raise RecordingError(f"{self.path}: unreadable chunk ({err})") from None
        out = [
            (self._channels[m.channel_id].topic, m.log_time, m.data)
            for m in records
            if m.channel_id in self._channels
        ]
        out.sort(key=lambda m: m[1])
        return out

    @property
    def indexed(self) -> bool:
        """Whether chunks carry message indexes (a finished file): :meth:`chunk_topic_index`,
        :meth:`chunk_records` and :func:`record_message` then read one message of a chunk
        without parsing the others."""
        return self._reader is not None

    def chunk_topic_index(self, key: int, topic: str) -> tuple[NDArray, NDArray]:
        """``(log times ns, offsets)`` of ``topic``'s messages in chunk ``key`` (offsets into
        :meth:`chunk_records`), by time, as ``uint64`` arrays; empty when the chunk has none or
        the file no index. One read of the chunk's MessageIndex record, parsed by numpy."""
        empty = np.empty(0, dtype=np.uint64)
        if self._reader is None:
            return empty, empty
        index = self._chunk_index_by_key().get(key)
        cid = self._topic_ids().get(topic)
        if index is None or cid is None or cid not in index.message_index_offsets:
            return empty, empty
        assert self._file is not None
        try:
            self._file.seek(index.message_index_offsets[cid])
            head = self._file.read(1 + 8 + 2 + 4)
            opcode, _length, _cid, size = struct.unpack("<BQHI", head)
            if opcode != 0x07 or size % 16:
                raise ValueError(f"not a message index (opcode {opcode:#x})")
            pairs = np.frombuffer(self._file.read(size), dtype="<u8").reshape(-1, 2)
        except (ValueError, struct.error, OSError) as err:
            raise RecordingError(f"{self.path}: unreadable message index ({err})") from None
        order = np.argsort(pairs[:, 0], kind="stable")
        return pairs[order, 0].copy(), pairs[order, 1].copy()

    def chunk_records(self, key: int) -> bytes:
        """The decompressed records of chunk ``key`` (finished files)."""
        assert self._file is not None and self._reader is not None
        from mcap.data_stream import ReadDataStream
        from mcap.stream_reader import get_chunk_data_stream

        try:
            self._file.seek(key + 1 + 8)
            chunk = Chunk.read(ReadDataStream(self._file))
            stream, _length = get_chunk_data_stream(chunk)
            return stream.read(_length)
        except (McapError, ValueError, EOFError, OSError) as err:
            raise RecordingError(f"{self.path}: unreadable chunk ({err})") from None

    def _chunk_index_by_key(self) -> dict[int, Any]:
        cached = getattr(self, "_index_by_key", None)
        if cached is None:
            summary = self._reader.get_summary()
            cached = {ci.chunk_start_offset: ci for ci in summary.chunk_indexes}
            self._index_by_key = cached
        return cached

    def _topic_ids(self) -> dict[str, int]:
        cached = getattr(self, "_ids_by_topic", None)
        if cached is None:
            cached = {ch.topic: cid for cid, ch in self._channels.items()}
            self._ids_by_topic = cached
        return cached

    def decode(self, topic: str, data: bytes) -> Any:
        """One message's body from its encoded bytes (a dict for JSON channels, the protobuf
        message for Foxglove ones)."""
        for cid, ch in self._channels.items():
            if ch.topic == topic:
                return self._decode(cid, data)
        raise RecordingError(f"{self.path}: no channel {topic!r}")

    def captured_frame(
        self, capture: dict[str, Any], depth_msg: Any, log_time_s: float
    ) -> CapturedFrame:
        """A :class:`CapturedFrame` from a decoded capture message and its decoded depth image
        (:class:`RecordingError` naming the message when they do not fit)."""
        return self._frame(capture, depth_msg, log_time_s)

    def seek(
        self, t_s: float, topics: Iterable[str] | None = None, window_s: float = 1.0
    ) -> dict[str, RecordedMessage]:
        """The newest message of each channel at or before ``t_s`` and at most ``window_s`` older
        (a timeline's cursor: what was on each channel then)."""
        out: dict[str, RecordedMessage] = {}
        for msg in self.messages(topics, t_s - window_s, t_s + 1e-9):
            out[msg.topic] = msg
        return out

    def estimates(
        self,
        cameras: Iterable[str] | None = None,
        start_s: float | None = None,
        end_s: float | None = None,
    ) -> Iterator[Any]:
        """Recorded :class:`~hapticloud.core.perception.SurfaceEstimate` s (from the estimate
        channels' wire dicts), in log-time order."""
        from ..control.messages import estimate_from_dict

        names = self.cameras_with_estimates() if cameras is None else list(cameras)
        topics = [fmt.estimate_topic(c) for c in names]
        for msg in self.messages(topics, start_s, end_s):
            try:
                yield estimate_from_dict(msg.data)
            except (KeyError, TypeError, ValueError) as err:
                raise RecordingError(
                    f"{self.path}: {msg.topic} at {msg.log_time_s:.3f} s: bad estimate ({err})"
                ) from None

    def cameras_with_estimates(self) -> list[str]:
        return [
            c
            for topic in self.channels
            if (c := fmt.camera_of(topic)) is not None and topic == fmt.estimate_topic(c)
        ]

    def frames(
        self,
        cameras: Iterable[str] | None = None,
        start_s: float | None = None,
        end_s: float | None = None,
    ) -> Iterator[CapturedFrame]:
        """Recorded camera frames (full-size, zeros outside the stored rectangle) with their
        HIP, exclusion shapes and estimate ``seq``, in recording order."""
        names = self.cameras if cameras is None else list(cameras)
        topics = [t for c in names for t in (fmt.depth_topic(c), fmt.capture_topic(c))]
        pending_depth: dict[tuple[str, float], Any] = {}
        pending_capture: dict[tuple[str, float], Any] = {}
        for msg in self.messages(topics, start_s, end_s):
            cam = fmt.camera_of(msg.topic)
            assert cam is not None
            key = (cam, msg.log_time_s)
            if msg.topic == fmt.depth_topic(cam):
                capture = pending_capture.pop(key, None)
                if capture is None:
                    pending_depth[key] = msg.data
                    continue
                depth = msg.data
            else:
                depth = pending_depth.pop(key, None)
                if depth is None:
                    pending_capture[key] = msg.data
                    continue
                capture = msg.data
            yield self._frame(capture, depth, msg.log_time_s)

    def _frame(self, cap: dict[str, Any], depth_msg: Any, log_time_s: float) -> CapturedFrame:
        where = f"{self.path}: {fmt.capture_topic(cap.get('camera', '?'))} at {log_time_s:.3f} s"
        try:
            k = CameraIntrinsics(
                int(cap["width"]), int(cap["height"]), cap["fx"], cap["fy"], cap["cx"], cap["cy"]
            )
            pose = np.asarray(cap["pose_world_camera"], dtype=np.float64).reshape(4, 4)
            roi = tuple(int(v) for v in cap["roi"])
            pixels = fmt.decode_depth(depth_msg)
            frame = frame_from_roi(cap["t"], cap["camera"], pixels, roi, k, pose)
            exclude = tuple(primitive_from_dict(p) for p in cap["exclude"])
            hip = np.asarray(cap["hip"], dtype=np.float64)
            return CapturedFrame(frame, roi, hip, exclude, int(cap["seq"]), log_time_s)  # type: ignore[arg-type]
        except (KeyError, TypeError, ValueError) as err:
            raise RecordingError(f"{where}: bad frame ({err})") from None


_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, length, channel, sequence, log, publish time


def record_message(records: bytes, offset: int) -> tuple[int, bytes]:
    """``(log time ns, data)`` of the Message record at ``offset`` of a chunk's records."""
    opcode, length, _cid, _seq, log_time, _pub = _MESSAGE_HEAD.unpack_from(records, offset)
    if opcode != 0x05:
        raise RecordingError(f"record at {offset}: opcode {opcode:#x}, not a message")
    start = offset + 9 + 22
    return log_time, bytes(records[start : offset + 9 + length])


def _single(message: Message) -> Chunk:
    """A one-message stand-in chunk (files written without chunking)."""
    from mcap.records import Chunk as _Chunk

    chunk = _Chunk(
        compression="",
        data=b"",
        message_start_time=message.log_time,
        message_end_time=message.log_time,
        uncompressed_crc=0,
        uncompressed_size=0,
    )
    chunk._single = message  # type: ignore[attr-defined]
    return chunk


def _messages_of(chunk: Chunk) -> list[Message]:
    single = getattr(chunk, "_single", None)
    if single is not None:
        return [single]
    return [r for r in breakup_chunk(chunk) if isinstance(r, Message)]


__all__ = ["ChannelInfo", "ChunkSpan", "RecordedMessage", "Recording", "record_message"]
