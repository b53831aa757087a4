"""``hapticloud recover FILE OUT``: an unfinished recording rewritten complete and indexed.

Every message of the whole chunks of ``FILE`` (see :class:`~.reader.Recording`) is copied, with
its channels, schemas and metadata, into ``OUT``, which is then finished (summary, chunk index)
and opened again by its index to check that it holds every message the original had.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from hapticloud.core.errors import RecordingError
from mcap.writer import CompressionType, Writer

from .reader import Recording
from .writer import CHUNK_BYTES, software_version


def recover(src: str | os.PathLike[str], out: str | os.PathLike[str]) -> dict[str, Any]:
    """Rewrite ``src`` as ``out``; returns ``{"messages", "was_finished", "start_s", "end_s",
    "bytes", "truncation"}``.

    Raises
    ------
    RecordingError
        ``src`` is not a readable recording, ``out`` is ``src``, or the check of ``out`` fails.
    """
    if Path(out).resolve() == Path(src).resolve():
        raise RecordingError(f"{out}: the output must not be the file being recovered")
    with Recording.open(src) as rec:
        info = {
            "messages": rec.message_count,
            "was_finished": rec.finished,
            "truncation": rec.truncation,
            "start_s": rec.start_s,
            "end_s": rec.end_s,
        }
        channels = rec._channels
        schemas = rec._schemas
        try:
            stream = open(out, "wb")
        except OSError as err:
            raise RecordingError(f"{out}: cannot be written ({err.strerror})") from None
        writer = Writer(stream, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        writer.start(profile="", library=f"hapticloud {software_version()} (recover)")
        for name, data in rec.metadata.items():
            writer.add_metadata(name, data)
        schema_ids = {
            sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in schemas.items()
        }
        by_topic = {}
        for ch in channels.values():
            by_topic[ch.topic] = writer.register_channel(
                ch.topic, ch.message_encoding, schema_ids.get(ch.schema_id, 0), dict(ch.metadata)
            )
        copied = 0
        for topic, ns, data in rec.raw_messages():
            writer.add_message(by_topic[topic], ns, data, ns)
            copied += 1
        writer.finish()
        stream.close()
    with Recording.open(out) as check:
        if not check.finished or check.message_count != copied:
            raise RecordingError(
                f"{out}: check failed: {check.message_count} messages read back of {copied} "
                f"written ({'indexed' if check.finished else 'not indexed'})"
            )
    info["bytes"] = os.path.getsize(out)
    info["messages"] = copied
    return info


__all__ = ["recover"]
