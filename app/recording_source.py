"""A recording as a snapshot source: the window's views and plots show it at a cursor time.

:class:`RecordingSource` implements the window's
:class:`~hapticloud.hardware.live.contract.SnapshotSource` over a
:class:`~hapticloud.hardware.recording.cursor.RecordingPlayer` (the cursor and its decoding
thread, the timeline scan, the re-run process: all in the hardware layer, none of it Qt). Each
:meth:`RecordingSource.latest` composes a :class:`~hapticloud.hardware.live.contract.Snapshot`
from the player's
newest decoded view, once per new view, new timeline data or new re-run rows:

* every camera's newest frame at or before the cursor: its crop (what perception read) as the
  camera's cloud, every 4th pixel of its stored rectangle as the scene points, the estimate
  recorded for that frame; a camera without a frame yet is shown empty;
* the HIP (newest control state, else the newest frame's), the robot's exclusion shapes of the
  newest frame, the fused surface (recorded, or re-computed from the recorded estimates);
* the plots' history: the last 10 s of estimates and control states before the cursor, from the
  timeline scan.

Times are seconds from the recording's first message (a session on the monotonic clock starts at
0 like a simulated run). No thread here: the player has them; the window polls.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np
from hapticloud.core.geometry.primitives import Box, Capsule, Primitive, Sphere
from hapticloud.core.perception import STAGES, SurfaceEstimate
from hapticloud.hardware.live.contract import (
    CONTROL_COLUMNS,
    FRAME_COLUMNS,
    HISTORY_S,
    TICK_COLUMNS,
    CameraFrame,
    CameraInfo,
    History,
    LiveConfig,
    SceneGeometry,
    Snapshot,
    SourceState,
)
from hapticloud.hardware.recording.cursor import CameraAt, CursorView, RecordingPlayer
from hapticloud.hardware.recording.timeline import TimelineData
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
_KINDS = {Sphere: "sphere", Capsule: "capsule", Box: "box"}


def is_recording(path: str | Path) -> bool:
    """Whether ``path`` names a recording: a ``.mcap`` name, or a file starting with the MCAP
    magic (a file that does not exist counts by its name only)."""
    p = Path(path)
    if p.suffix.lower() == ".mcap":
        return True
    try:
        with open(p, "rb") as f:
            return f.read(8) == b"\x89MCAP0\r\n"
    except OSError:
        return False


class RecordingSource:
    """A recording shown at the player's cursor (see the module docstring).

    Parameters
    ----------
    player
        An opened (not started) :class:`RecordingPlayer`; :meth:`open` makes one from a path.
    config
        The window's parameters (the recorded perception and fusion by default); a re-run uses
        the newest one asked for (:meth:`request_config`).
    """

    def __init__(self, player: RecordingPlayer, config: LiveConfig | None = None) -> None:
        self.player = player
        layout = player.layout
        self._config = config or recorded_live_config(player)
        self._version = 0
        self._geometry = SceneGeometry(
            name=layout.name,
            cameras=tuple(CameraInfo(c.name, c.origin, c.axis) for c in layout.cameras),
            bodies=(),
            r_hip_m=layout.r_hip_m,
            robot_shapes=layout.shapes,
            description=layout.description,
        )
        self._state = SourceState.STARTING
        self._message = ""
        self._latest: Snapshot | None = None
        self._key: tuple[int, int, int] | None = None
        self._seq = 0
        self._composed_view = -1
        self.start_s = player.start_s

    @classmethod
    def open(cls, path: str | Path, config: LiveConfig | None = None) -> RecordingSource:
        """Open ``path`` (index only; :class:`RecordingError`, one line, if it is not a
        readable recording)."""
        return cls(RecordingPlayer(path), config)

    # ----- SnapshotSource -------------------------------------------------------------------------
    @property
    def geometry(self) -> SceneGeometry:
        return self._geometry

    @property
    def state(self) -> SourceState:
        return self._state

    @property
    def message(self) -> str:
        return self._message

    def start(self) -> None:
        self.player.start()
        self._state = SourceState.RUNNING

    def latest(self) -> Snapshot | None:
        """The snapshot at the cursor (``None`` before the first view is decoded)."""
        view = self.player.view
        if view is None:
            return None
        rerun = self.player.rerun
        key = (view.seq, id(self.player.timeline), 0 if rerun is None else rerun.done)
        if key != self._key:
            self._key = key
            self._seq += 1
            self._latest = self._compose(view, self.player.timeline)
        return self._latest

    def request_config(self, config: LiveConfig) -> int:
        """Keep ``config`` for the next re-run (a recording's frames do not change)."""
        self._config = config
        self._version += 1
        return self._version

    @property
    def requested_config(self) -> LiveConfig:
        return self._config

    def emergency_stop(self, reason: str = "paused") -> None:
        """Nothing moves in a recording: pause it."""
        self.player.pause()

    def close(self, timeout_s: float = 2.0) -> None:
        self.player.close(timeout_s)
        self._state = SourceState.STOPPED

    # ----- composing ------------------------------------------------------------------------------
    def rel(self, t: float) -> float:
        """Seconds from the recording's start."""
        return t - self.start_s

    def _compose(self, view: CursorView, timeline: TimelineData) -> Snapshot:
        t = self.rel(view.t)
        hip = view.hip if view.hip is not None else np.full(3, np.nan)
        if not np.isfinite(hip).all():
            hip = np.zeros(3)
        cameras = tuple(self._camera_frame(c, timeline, view.t) for c in view.cameras)
        fused = view.fused
        if fused is not None:
            fused = dataclasses.replace(fused, t=self.rel(fused.t))
        player = self.player
        now = time.monotonic()
        # "captured": when the view was asked for (a seek's latency to the screen); a view shown
        # again with new timeline or re-run data counts from now.
        captured = view.requested if view.seq != self._composed_view else now
        self._composed_view = view.seq
        return Snapshot(
            seq=self._seq,
            t=t,
            published=now,
            captured=captured,
            state=SourceState.RUNNING,
            message=view.error,
            hip=_frozen(hip),
            robot=self._robot(view.robot),
            cameras=cameras,
            fused=fused,
            fused_d_proj_m=view.fused_d_proj_m,
            truth=None,
            body_offsets=(),
            config=self._config,
            config_version=self._version,
            real_time_factor=player.speed if player.playing else 0.0,
            history=self.history(view.t, timeline),
        )

    def _robot(self, robot: tuple[Primitive, ...]) -> tuple[Primitive, ...]:
        """The shapes that fit the view's slots (kinds in order; the first misfit ends it)."""
        slots = self._geometry.robot_shapes
        out = []
        for prim, kind in zip(robot, slots, strict=False):
            if _KINDS.get(type(prim)) != kind:
                break
            out.append(prim)
        return tuple(out)

    def _camera_frame(self, cam: CameraAt, timeline: TimelineData, t_abs: float) -> CameraFrame:
        rel_t = self.rel(cam.log_time_s) if math.isfinite(cam.log_time_s) else self.rel(t_abs)
        est = cam.estimate
        points = cam.cropped if len(cam.cropped) else None
        if est is None:
            est = SurfaceEstimate.invalid(
                rel_t,
                cam.name,
                "no frame yet" if cam.frame is None else "no estimate recorded",
                points=points,
            )
        else:
            est = dataclasses.replace(est, t=rel_t, points=points)
        d_proj = math.nan
        if est.valid and cam.frame is not None:
            d_proj = est.d_proj(cam.frame.hip, self._geometry.r_hip_m)
        rate = math.nan
        lane = timeline.camera(cam.name)
        if lane is not None and len(lane.t):
            lo = np.searchsorted(lane.t, t_abs - 1.0)
            hi = np.searchsorted(lane.t, t_abs, side="right")
            if hi - lo >= 2:
                span = lane.t[hi - 1] - lane.t[lo]
                rate = (hi - lo - 1) / span if span > 0 else math.nan
        return CameraFrame(
            name=cam.name,
            estimate=est,
            context=cam.context,
            render_ms=math.nan,
            rate_hz=rate,
            d_proj_m=d_proj,
            error_mm=math.nan,
            normal_error_deg=math.nan,
        )

    def history(self, t_abs: float, timeline: TimelineData) -> History:
        """The plots' rows for the :data:`HISTORY_S` before ``t_abs`` (relative times)."""
        lo_t = t_abs - HISTORY_S
        ctl = timeline.control
        c_lo = np.searchsorted(ctl.t, lo_t)
        c_hi = np.searchsorted(ctl.t, t_abs, side="right")
        ct = ctl.t[c_lo:c_hi]
        margin = ctl.margin_mm[c_lo:c_hi]
        parts = []
        n_stage = len(STAGES) + 1
        for i, lane in enumerate(timeline.cameras):
            lo = np.searchsorted(lane.t, lo_t)
            hi = np.searchsorted(lane.t, t_abs, side="right")
            n = hi - lo
            if n <= 0:
                continue
            tt = lane.t[lo:hi]
            true_dp = (
                np.interp(tt, ct, margin, left=np.nan, right=np.nan)
                if len(ct) and np.isfinite(margin).any()
                else np.full(n, np.nan)
            )
            block = np.column_stack(
                (
                    tt - self.start_s,
                    np.full(n, float(i)),
                    lane.valid[lo:hi].astype(np.float64),
                    lane.d_proj_mm[lo:hi],
                    true_dp,
                    np.full((n, 3), np.nan),  # error, normal error, fused error
                    np.full((n, n_stage), np.nan),
                )
            )
            parts.append(block)
        width = len(FRAME_COLUMNS)
        frames = np.concatenate(parts) if parts else np.empty((0, width))
        frames = frames[:, :width]
        if len(frames):
            frames = frames[np.argsort(frames[:, 0], kind="stable")]
        ticks = np.column_stack(
            (
                ct - self.start_s,
                ctl.fused_valid[c_lo:c_hi].astype(np.float64),
                ctl.d_proj_mm[c_lo:c_hi],
                np.full(len(ct), np.nan),
            )
        ).reshape(-1, len(TICK_COLUMNS))
        frames.setflags(write=False)
        ticks.setflags(write=False)
        return History(frames, ticks)

    def control_history(self) -> NDArray[np.float64]:
        """The control tab's rows (:data:`~hapticloud.hardware.live.contract.CONTROL_COLUMNS`)
        for the last :data:`HISTORY_S` before the cursor: what the recording has of them (tick
        time, misses, d_proj, state); approach and force are not recorded (NaN)."""
        from hapticloud.hardware.control import STATE_CODES

        view = self.player.view
        ctl = self.player.timeline.control
        if view is None or not len(ctl.t):
            return np.empty((0, len(CONTROL_COLUMNS)))
        lo = np.searchsorted(ctl.t, view.t - HISTORY_S)
        hi = np.searchsorted(ctl.t, view.t, side="right")
        n = hi - lo
        states = np.array([STATE_CODES.get(s, -1) for s in ctl.state[lo:hi]], dtype=np.float64)
        misses = ctl.misses[lo:hi]
        return np.column_stack(
            (
                ctl.t[lo:hi] - self.start_s,
                ctl.tick_us[lo:hi],
                ctl.tick_us[lo:hi],
                np.where(np.isfinite(misses), misses, 0.0),
                np.full(n, np.nan),
                np.full(n, np.nan),
                ctl.d_proj_mm[lo:hi],
                states,
            )
        ).reshape(-1, len(CONTROL_COLUMNS))


def recorded_live_config(player: RecordingPlayer) -> LiveConfig:
    """The window's parameters for a recording: its recorded perception and fusion tables."""
    layout = player.layout
    return dataclasses.replace(LiveConfig(), perception=layout.perception, fusion=layout.fusion)


def _frozen(a: FloatArray) -> FloatArray:
    out = np.array(a, dtype=np.float64)
    out.setflags(write=False)
    return out


__all__ = ["RecordingSource", "is_recording", "recorded_live_config"]
