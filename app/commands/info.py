"""``hapticloud info RECORDING``: what a recording holds, and whether it is finished."""

from __future__ import annotations

import argparse
import json
import sys


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "info",
        help="what a recording (.mcap) holds: source, scene, duration, channels, cameras",
        description="Prints a recording's metadata, time span and channels (topic, schema, "
        "messages). Reads the index of a finished file only; an unfinished one (the recording "
        "was killed or the disk filled) is read up to its last whole chunk and said to be "
        "unfinished ('hapticloud recover' rewrites it indexed).",
    )
    parser.add_argument("recording", metavar="RECORDING", help="the .mcap file")
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hapticloud.hardware.recording.reader import Recording

    with Recording.open(args.recording) as rec:
        info = rec.info
        data = {
            "path": str(rec.path),
            "finished": rec.finished,
            "truncation": rec.truncation,
            "format_version": rec.format_version,
            "source": info.get("source", ""),
            "scene": info.get("scene", ""),
            "clock": info.get("clock", ""),
            "created_utc": info.get("created_utc", ""),
            "software": info.get("software", ""),
            "frames": info.get("frames", ""),
            "start_s": rec.start_s,
            "end_s": rec.end_s,
            "duration_s": rec.duration_s,
            "messages": rec.message_count,
            "cameras": rec.cameras,
            "channels": [
                {
                    "topic": c.topic,
                    "schema": c.schema,
                    "encoding": c.encoding,
                    "messages": c.messages,
                }
                for c in rec.channels.values()
            ],
        }
    if args.json:
        json.dump(data, sys.stdout, indent=2)
        print()
        return 0
    state = (
        "finished (indexed)"
        if data["finished"]
        else (
            f"UNFINISHED: read up to its last whole chunk ({data['truncation']}); "
            "'hapticloud recover' rewrites it indexed"
        )
    )
    print(f"{data['path']}: hapticloud recording, format version {data['format_version']}, {state}")
    print(
        f"source: {data['source']}; scene: {data['scene'] or '-'}; clock: {data['clock']}; "
        f"frames: {data['frames']}; written by {data['software']} at {data['created_utc']}"
    )
    print(
        f"time: {data['start_s']:.3f} s to {data['end_s']:.3f} s ({data['duration_s']:.3f} s), "
        f"{data['messages']} messages; cameras: {', '.join(data['cameras']) or 'none'}"
    )
    width = max((len(c["topic"]) for c in data["channels"]), default=5)
    for c in data["channels"]:
        print(f"  {c['topic']:<{width}}  {c['schema']:<28} {c['encoding']:<9} {c['messages']:>7}")
    return 0
