"""A re-run of a recording with other parameters, in a process of its own, streamed back.

:class:`ReRun` spawns a process that opens the recording, feeds every recorded frame in order
through :func:`hapticloud.core.recording.replay` (each camera from its first frame, so the ICP
memory builds as it did) with the given perception and fusion parameters, and sends back, every
few dozen frames, compact rows: per frame its log time, camera, the new estimate (validity,
centroid, normal) and the recorded one, the HIP, and the fused centroids of both. The parent
polls (:meth:`ReRun.poll`) and never waits; :meth:`ReRun.cancel` ends it. Points are not kept
(``keep_points`` off): a 10-minute re-run holds a few MB.

A process, not a thread: perception is CPU work that would take the GIL from the window that
shows the recording.
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing as mp
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from hapticloud.core.fusion import FusionConfig
from hapticloud.core.perception import PerceptionConfig
from numpy.typing import NDArray

#: Rows sent back per message.
BATCH = 60
#: Columns of a re-run row (one per frame).
ROW_COLUMNS = (
    "t",  # log time (s)
    "camera",  # index into the cameras given
    "new_valid",
    "new_cx",
    "new_cy",
    "new_cz",
    "new_nx",
    "new_ny",
    "new_nz",
    "rec_valid",  # NaN: no recorded estimate for the frame
    "rec_cx",
    "rec_cy",
    "rec_cz",
    "rec_nx",
    "rec_ny",
    "rec_nz",
    "hip_x",
    "hip_y",
    "hip_z",
    "new_fx",  # fused centroid of the new estimates (NaN: invalid)
    "new_fy",
    "new_fz",
    "rec_fx",
    "rec_fy",
    "rec_fz",
    "roi_exceeded",
)
COL = {name: i for i, name in enumerate(ROW_COLUMNS)}


@dataclass(frozen=True)
class ReRunRows:
    """The rows received so far (``(N, len(ROW_COLUMNS))``, by frame order) and helpers."""

    rows: NDArray[np.float64]
    cameras: tuple[str, ...]

    def column(self, name: str) -> NDArray[np.float64]:
        return self.rows[:, COL[name]]

    def camera_rows(self, name: str) -> NDArray[np.float64]:
        if name not in self.cameras:
            return self.rows[:0]
        return self.rows[self.rows[:, COL["camera"]] == self.cameras.index(name)]

    def d_proj_mm(self, rows: NDArray[np.float64], r_hip_m: float, which: str = "new") -> NDArray:
        """``d_proj`` (mm) of the ``which`` (new / rec) estimates of ``rows`` (NaN: invalid)."""
        c = rows[:, [COL[f"{which}_c{a}"] for a in "xyz"]]
        n = rows[:, [COL[f"{which}_n{a}"] for a in "xyz"]]
        h = rows[:, [COL[f"hip_{a}"] for a in "xyz"]]
        d = np.einsum("ij,ij->i", c - h, -n) - r_hip_m
        return np.where(rows[:, COL[f"{which}_valid"]] == 1.0, 1e3 * d, np.nan)


def _row(cam_index: int, log_t: float, row: Any, hip: Any) -> list[float]:
    new, rec = row.new, row.recorded
    out = [log_t, float(cam_index), float(new.valid), *map(float, new.centroid)]
    out += list(map(float, new.normal))
    if rec is None:
        out += [math.nan] * 7
    else:
        out += [float(rec.valid), *map(float, rec.centroid), *map(float, rec.normal)]
    out += [float(x) for x in hip]
    for fused in (row.new_fused, row.recorded_fused):
        out += [math.nan] * 3 if fused is None else [float(x) for x in fused]
    out.append(float(row.roi_exceeded))
    return out


def _child(
    path: str,
    perception: PerceptionConfig,
    fusion: FusionConfig,
    cameras: list[str],
    conn: Any,
) -> None:
    from hapticloud.core.recording import replay
    from hapticloud.core.threads import settle_numerics

    from .reader import Recording

    settle_numerics(1)
    try:
        rec = Recording.open(path)
        total = sum(
            info.messages
            for topic, info in rec.channels.items()
            if topic.endswith("/capture") and topic.split("/")[2] in cameras
        )
        conn.send(("total", total))
        recorded = {(e.camera, e.seq): e for e in rec.estimates()}
        log_times: list[tuple[int, float, Any]] = []
        index = {name: i for i, name in enumerate(cameras)}

        def frames() -> Any:
            for cap in rec.frames(cameras):
                log_times.append((index.get(cap.camera, -1), cap.log_time_s, cap.hip))
                yield cap

        batch: list[list[float]] = []
        done = [0]

        def on_row(row: Any) -> None:
            cam, log_t, hip = log_times[done[0]]
            done[0] += 1
            batch.append(_row(cam, log_t, row, hip))
            if len(batch) >= BATCH:
                conn.send(("rows", np.array(batch, dtype=np.float64)))
                batch.clear()

        perception = dataclasses.replace(perception, keep_points=False)
        t0 = time.perf_counter()
        result = replay(frames(), recorded, perception, fusion, on_row=on_row)
        if batch:
            conn.send(("rows", np.array(batch, dtype=np.float64)))
        summary = result.summary()
        summary["wall_s"] = time.perf_counter() - t0
        summary["real_time_factor"] = rec.duration_s / max(summary["wall_s"], 1e-9)
        conn.send(("done", summary))
        rec.close()
    except Exception as err:
        text = str(err).splitlines()[0] if str(err) else traceback.format_exc().splitlines()[-1]
        try:
            conn.send(("error", text))
        except OSError:
            pass


class ReRun:
    """A re-run in progress (see the module docstring). Poll with :meth:`poll` from any one
    thread; read :attr:`rows`, :attr:`done`, :attr:`total`, :attr:`summary`, :attr:`error`."""

    def __init__(
        self,
        path: str | Path,
        perception: PerceptionConfig,
        fusion: FusionConfig,
        cameras: list[str],
    ) -> None:
        self.perception = perception
        self.fusion = fusion
        self.cameras = tuple(cameras)
        self.total = 0
        self.summary: dict[str, Any] | None = None
        self.error = ""
        self.started = time.monotonic()
        self._chunks: list[NDArray[np.float64]] = []
        # Rows go into a buffer that doubles when full: taking a batch costs its own size, not
        # the whole re-run's (a 10-minute recording has 36,000 frames).
        self._buf = np.empty((1024, len(ROW_COLUMNS)))
        self._n = 0
        self.rows = ReRunRows(self._buf[:0], self.cameras)
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=_child,
            args=(str(path), perception, fusion, list(cameras), child),
            name="hapticloud-rerun",
            daemon=True,
        )
        self._proc.start()
        child.close()
        self.cancelled = False

    @property
    def done(self) -> int:
        return len(self.rows.rows)

    @property
    def finished(self) -> bool:
        return self.summary is not None or bool(self.error) or self.cancelled

    def poll(self) -> bool:
        """Take what the process sent (never blocks); True if anything new arrived."""
        new = False
        try:
            while not self.finished and self._conn.poll(0):
                kind, payload = self._conn.recv()
                new = True
                if kind == "total":
                    self.total = int(payload)
                elif kind == "rows":
                    self._chunks.append(payload)
                elif kind == "done":
                    self.summary = dict(payload)
                elif kind == "error":
                    self.error = str(payload)
        except (EOFError, OSError):
            if not self.finished:
                self.error = "the re-run process ended unexpectedly"
                new = True
        if new and self._chunks:
            for chunk in self._chunks:
                self._append(chunk)
            self._chunks.clear()
            self.rows = ReRunRows(self._buf[: self._n], self.cameras)
        if self.finished and self._proc.is_alive() and self.summary is not None:
            self._proc.join(0.1)
        return new

    def _append(self, rows: NDArray[np.float64]) -> None:
        need = self._n + len(rows)
        if need > len(self._buf):
            grown = np.empty((max(need, 2 * len(self._buf)), len(ROW_COLUMNS)))
            grown[: self._n] = self._buf[: self._n]
            self._buf = grown
        self._buf[self._n : need] = rows
        self._n = need

    def wait(self, timeout_s: float = 60.0) -> bool:
        """Poll until finished (tests, benchmarks); True if it finished in time."""
        end = time.monotonic() + timeout_s
        while not self.finished and time.monotonic() < end:
            self.poll()
            time.sleep(0.02)
        self.poll()
        return self.finished

    def cancel(self) -> None:
        """Stop the process (idempotent)."""
        if not self.finished:
            self.cancelled = True
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(2.0)
        self._conn.close()


__all__ = ["BATCH", "COL", "ROW_COLUMNS", "ReRun", "ReRunRows"]
