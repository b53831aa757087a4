"""``hapticloud bench seek``: how fast a recording opens and how fast a seek shows its frame.

Headless figures (this module): the time to open a recording by its index and read its layout
(what ``hapticloud app FILE.mcap`` does before the window), the time to the first decoded view,
the timeline scan's duration, and per seek to a random time the decode latency (the cursor
thread: from the request to a :class:`~.cursor.CursorView` holding every camera's newest frame
at or before it). The window's seek-to-screen figure (the 3D view painted) is measured by
:mod:`hapticloud.app.recording_bench`.
"""

from __future__ import annotations

import os
import random
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .cursor import RecordingPlayer


def latency_stats(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)
    if not ordered:
        return {"n": 0}
    p95 = ordered[min(len(ordered) - 1, round(0.95 * (len(ordered) - 1)))]
    return {
        "n": len(ordered),
        "median": statistics.median(ordered),
        "p95": p95,
        "max": ordered[-1],
    }


def seek_times(player: RecordingPlayer, n: int, seed: int = 0) -> list[float]:
    """``n`` random cursor times (seeded), spread over the whole recording."""
    rng = random.Random(seed)
    return [rng.uniform(player.start_s, player.end_s) for _ in range(n)]


def wait_view(player: RecordingPlayer, t: float, timeout_s: float = 30.0) -> Any:
    end = time.monotonic() + timeout_s
    while True:
        view = player.view
        if view is not None and view.t == min(max(t, player.start_s), player.end_s):
            return view
        if time.monotonic() > end:
            raise TimeoutError(f"no view at {t:.3f} s within {timeout_s:g} s")
        time.sleep(0.0005)


def seek_bench(
    path: str | Path, seeks: int = 50, seed: int = 0, say: Callable[[str], None] = print
) -> dict[str, Any]:
    """The figures (ms): ``open_ms``, ``first_view_ms``, ``scan_s``, ``seek_ms`` stats (after
    the scan, as a user scrubs), ``seek_during_scan_ms`` (the first seeks, while it reads)."""
    path = Path(path)
    t0 = time.perf_counter()
    player = RecordingPlayer(path)
    open_ms = 1e3 * (time.perf_counter() - t0)
    say(f"opened {path.name} in {open_ms:.0f} ms (index and layout)")
    try:
        t1 = time.perf_counter()
        player.start()
        wait_view(player, player.start_s)
        first_ms = 1e3 * (time.perf_counter() - t1)
        early = []
        for t in seek_times(player, 5, seed + 1):
            player.seek(t)
            early.append(wait_view(player, t).decode_ms)
        while not player.timeline.complete:
            time.sleep(0.01)
        scan_s = time.perf_counter() - t1
        say(f"timeline read in {scan_s:.1f} s")
        decode = []
        for t in seek_times(player, seeks, seed):
            player.seek(t)
            view = wait_view(player, t)
            if any(c.frame is None for c in view.cameras):
                raise RuntimeError(f"seek to {t:.3f} s: a camera without its frame")
            decode.append(view.decode_ms)
        rec = player.rec
        return {
            "file": str(path),
            "bytes": os.path.getsize(path),
            "duration_s": rec.duration_s,
            "messages": rec.message_count,
            "finished": rec.finished,
            "open_ms": open_ms,
            "first_view_ms": first_ms,
            "scan_s": scan_s,
            "seek_during_scan_ms": latency_stats(early),
            "seek_ms": latency_stats(decode),
            "chunks_read": player._reader.chunks_read,
        }
    finally:
        player.close()


def seek_lines(result: dict[str, Any]) -> list[str]:
    def stats(s: dict[str, float]) -> str:
        if not s.get("n"):
            return "-"
        return f"median {s['median']:.0f}, p95 {s['p95']:.0f}, max {s['max']:.0f} ms (n={s['n']})"

    lines = [
        f"{result['file']}: {result['duration_s']:.1f} s, {result['bytes'] / 1e6:.0f} MB, "
        f"{result['messages']} messages, {'complete' if result['finished'] else 'UNFINISHED'}",
        f"  open (index only, layout): {result['open_ms']:.0f} ms   (target <= 2000 ms)",
        f"  first view: {result['first_view_ms']:.0f} ms; "
        f"timeline read in {result['scan_s']:.1f} s",
        "  seek, decode to view, while the timeline is read: "
        + stats(result["seek_during_scan_ms"]),
        f"  seek, decode to view: {stats(result['seek_ms'])}   (target <= 200 ms)",
    ]
    gui = result.get("gui")
    if gui:
        lines.append(
            f"  window: opened to its first frame painted in {gui['open_to_frame_ms']:.0f} ms; "
            f"seek, click to the 3D view painted ({gui['size']}): {stats(gui['seek_ms'])}"
        )
    return lines


__all__ = ["latency_stats", "seek_bench", "seek_lines", "seek_times", "wait_view"]
