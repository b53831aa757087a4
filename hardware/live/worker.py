"""The live worker: sim cameras -> perception -> fusion, one packet per camera frame.

The worker (:func:`run_worker`, run by :class:`~.source.LiveSource` in its own process or on a
thread) owns every object of the data path: the simulated world, one
:class:`~hapticloud.core.perception.CameraPipeline` per camera and the
:class:`~hapticloud.core.fusion.SurfaceFusion`. It renders each camera at 30 Hz (interleaved),
runs perception, adds the estimate to the fusion, samples the fusion at the control rate
(800 Hz) between frames, and sends one small :class:`Packet` per camera frame down a pipe. With a
session (:class:`SessionAttach`) it takes the HIP from the control process's shared state and
sends every estimate to the loop's fusion too.
"""

from __future__ import annotations

import dataclasses
import math
import queue
import time
import traceback
from dataclasses import dataclass
from typing import Any

import numpy as np
from hapticloud.core.fusion import FusedSurface, SurfaceFusion
from hapticloud.core.geometry.primitives import Primitive
from hapticloud.core.haptics import d_proj
from hapticloud.core.loop import admit
from hapticloud.core.perception import STAGES, CameraPipeline, SurfaceEstimate
from hapticloud.core.scene.schema import CameraSpec
from hapticloud.core.sim import GroundTruth
from hapticloud.core.studies.demo import CAMERA_RATE_HZ
from numpy.typing import NDArray

from .contract import CONTROL_RATE_HZ, TICK_COLUMNS, LiveConfig, SourceState
from .scenes import SimSettings, build_scene, robot_at, scene_spec, session_robot

FloatArray = NDArray[np.float64]

#: The scenes' default estimate gate (``cameras[i].min_quality``), as the control process uses.
ADMIT_MIN_QUALITY = CameraSpec().min_quality
#: Every n-th pixel (both directions) of a frame is kept as that camera's scene cloud: enough to
#: show what the crop removed (~5k points per camera), small enough to send at 60 frames/s. It is
#: rendered by a twin camera binned by this factor: perception's camera renders only the pixels
#: of the workspace sphere (what stage A reads), a 64th of the rays goes to the picture around it.
CONTEXT_STRIDE = 8
#: Behind real time by more than this (s), the sim clock stops catching up and slows down
#: instead (shown as the real-time factor): no burst of frames after a stall.
MAX_LAG_S = 0.1


@dataclass(frozen=True)
class SessionAttach:
    """What the worker needs to feed a running control process (picklable at spawn).

    ``estimates`` is :attr:`ControlProcess.estimate_connection` (the write end of its estimates
    pipe); ``state_block`` the name of its :class:`RobotStateBlock` (the robot's HIP and q, every
    tick). With a session, the worker takes the HIP from the block instead of the scripted path
    and sends every estimate to the loop, its time mapped onto ``time.monotonic()``.
    """

    estimates: Any
    state_block: str


class _SessionFeed:
    """The worker's end of a session: HIP in (shared memory), estimates out (pipe, never
    blocking: an estimate the pipe cannot take now is dropped and counted)."""

    def __init__(self, attach: SessionAttach) -> None:
        from hapticloud.hardware.control.shared_state import RobotStateBlock

        self._conn = attach.estimates
        self._block = RobotStateBlock.attach(attach.state_block)
        self.dropped = 0
        self.alive = True

    def state(self) -> tuple[FloatArray, FloatArray] | None:
        """The robot's HIP (m) and joint positions (rad) now, or ``None``."""
        if not self.alive:
            return None
        state = self._block.read()
        if state is None or not (np.isfinite(state.hip_m).all() and np.isfinite(state.q_rad).all()):
            return None
        return np.asarray(state.hip_m, dtype=np.float64), np.asarray(state.q_rad, np.float64)

    def hip(self) -> FloatArray | None:
        live = self.state()
        return None if live is None else live[0]

    def send(self, est: SurfaceEstimate, captured: float) -> None:
        if not self.alive:
            return
        import select

        from hapticloud.hardware.control.messages import send_estimate

        try:
            if not select.select((), (self._conn.fileno(),), (), 0.0)[1]:
                self.dropped += 1
                return
            # The loop's clock is time.monotonic(); the estimate's t is simulation time.
            send_estimate(self._conn, dataclasses.replace(est, t=captured))
        except (OSError, ValueError):
            self.alive = False  # the control process is gone: perception goes on alone

    def close(self) -> None:
        self._block.close()


@dataclass(frozen=True)
class RecordRequest:
    """Ask the worker to cut every frame it shows for a recording (``record``: a
    :class:`~hapticloud.core.recording.RecordConfig`), or to stop (``None``)."""

    record: Any


def _cut(depth: Any, hip: FloatArray, robot: Any, est: SurfaceEstimate, crop: Any, rec: Any) -> Any:
    """The frame cut as a recording stores it (the display's packet carries it to the GUI
    process, whose receiver hands it to the recorder: the control loop records nothing)."""
    from hapticloud.hardware.recording.recorder import cut_frame

    return cut_frame(depth, hip, robot, est, crop, rec)


@dataclass(frozen=True)
class FramePacket:
    """One camera frame, worker -> receiver. Estimates travel as field dicts (their stage_ms
    mapping proxy does not pickle) and are rebuilt, frozen, on the receiving side."""

    camera: int
    t: float
    captured: float
    hip: FloatArray
    robot: tuple[Primitive, ...]
    estimate: dict[str, Any]
    context: NDArray[np.float32]
    render_ms: float
    d_proj_m: float
    error_mm: float
    normal_error_deg: float
    fused: FusedSurface | None
    fused_d_proj_m: float
    truth: GroundTruth
    body_offsets: tuple[FloatArray, ...]
    frame_row: tuple[float, ...]
    tick_rows: FloatArray
    config: LiveConfig | None  # only when it changed
    config_version: int
    record: Any = None  # the frame cut for a recording (RecordRequest), or None


@dataclass(frozen=True)
class WorkerEnded:
    """Last message of a worker: why it ended."""

    state: SourceState
    message: str


def _estimate_fields(est: SurfaceEstimate) -> dict[str, Any]:
    out = {f.name: getattr(est, f.name) for f in dataclasses.fields(est)}
    out["stage_ms"] = dict(est.stage_ms)
    for name in ("points", "filled", "rejected"):
        if out[name] is not None:
            out[name] = out[name].astype(np.float32)  # half the bytes through the pipe
    return out


def _angle_deg(a: FloatArray, b: FloatArray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, float(a @ b)))))


def run_worker(
    settings: SimSettings,
    config: LiveConfig,
    conn: Any,
    requests: Any,
    stop: Any,
    session: SessionAttach | None = None,
) -> None:
    """Run the simulated data path until ``stop`` is set; one :class:`FramePacket` per frame.

    ``conn`` is the sending end of a pipe, ``requests`` a queue of ``(version, LiveConfig)``,
    :class:`RecordRequest` and :class:`SessionAttach`, ``stop`` an event. Runs in a worker
    process (or thread); everything it builds is its own. With ``session`` the HIP comes from
    the control process and every estimate goes to it.
    """
    feed = None
    if session is not None:
        try:
            feed = _SessionFeed(session)
        except (OSError, ValueError):
            feed = None  # the session is already gone: perception alone
    worker: _Worker | None = None
    try:
        worker = _Worker(settings, config, conn, requests, stop, feed)
        worker.run()
    except (BrokenPipeError, EOFError, OSError):
        return  # the receiver is gone: nobody to tell
    except Exception as err:  # report, do not die silently
        last = traceback.format_exception_only(err)[-1].strip()
        try:
            conn.send(WorkerEnded(SourceState.FAILED, f"source failed: {last}"))
        except OSError:
            pass
        return
    finally:
        feed = worker.feed if worker is not None else feed
        if feed is not None:
            feed.close()
    try:
        conn.send(WorkerEnded(SourceState.STOPPED, "stopped"))
    except OSError:
        pass


class _Worker:
    """The data path's objects and the loop's state, owned by the worker alone."""

    def __init__(
        self,
        settings: SimSettings,
        config: LiveConfig,
        conn: Any,
        requests: Any,
        stop: Any,
        feed: _SessionFeed | None,
    ) -> None:
        from hapticloud.core.threads import settle_numerics

        settle_numerics(1)
        scene = build_scene(settings)
        spec = scene_spec(settings.scene)
        self.settings, self.config, self.feed = settings, config, feed
        self.conn, self.requests, self.stop = conn, requests, stop
        self.world, self.cameras = scene.world, scene.cameras
        self.hip_path, self.world_at = spec.hip_path, spec.world_at
        self.r_hip = settings.r_hip_m
        self.pipes = [CameraPipeline(config.perception, camera=c.name) for c in self.cameras]
        self.twins = [_context_camera(c) for c in self.cameras]
        self.fusion = SurfaceFusion(config.fusion)
        self.tick_dt = 1.0 / CONTROL_RATE_HZ
        self.version, self.sent_version = 0, -1
        self.recording: Any = None  # a RecordConfig while the app records
        self.next_tick = 0.0
        self.wall0 = time.monotonic()

    def run(self) -> None:
        period = 1.0 / CAMERA_RATE_HZ
        k = 0
        while not self.stop.is_set():
            for j, cam in enumerate(self.cameras):
                # Interleaved like the demo: camera j fires j/n of a period after camera 0.
                t = k * period + j * period / len(self.cameras)
                if not self._wait_until(t):
                    return
                self._apply_requests(t)
                self._frame(j, cam, t)
            k += 1

    def _wait_until(self, t: float) -> bool:
        """Pace simulation time ``t`` to the wall clock; False once stopped."""
        speed = self.settings.speed
        delay = self.wall0 + t / speed - time.monotonic()
        if delay > 0:
            if self.stop.wait(delay):
                return False
        elif delay < -MAX_LAG_S:
            self.wall0 = time.monotonic() - t / speed
        return not self.stop.is_set()

    def _apply_requests(self, t: float) -> None:
        newest = None
        while True:  # drain: the newest request wins
            try:
                item = self.requests.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, RecordRequest):
                self.recording = item.record
            elif isinstance(item, SessionAttach):  # a session that came up after the start
                if self.feed is not None:
                    self.feed.close()
                try:
                    self.feed = _SessionFeed(item)
                except (OSError, ValueError):
                    self.feed = None
            else:
                newest = item
        if newest is None:
            return
        self.version, requested = newest
        if requested.perception != self.config.perception:
            for pipe in self.pipes:
                pipe.configure(requested.perception)
        if requested.fusion != self.config.fusion:
            self.fusion = SurfaceFusion(requested.fusion)
            self.next_tick = t
        self.config = requested

    def _robot_now(self, t: float) -> tuple[FloatArray, tuple[Primitive, ...], bool]:
        """The HIP, the robot's shapes and whether they are the session's (else scripted)."""
        live = self.feed.state() if self.feed is not None else None
        if live is None:
            hip = np.asarray(self.hip_path(t), dtype=np.float64)
            return hip, robot_at(self.settings, hip), False
        return live[0], session_robot(*live), True

    def _fuse(
        self, est: SurfaceEstimate, captured: float, t: float, hip: FloatArray, live: bool
    ) -> tuple[FusedSurface, float, FloatArray]:
        """Sample the fusion at the control rate up to this frame, then add the frame's estimate;
        the fused surface at ``t``, its projected distance and the ticks' history rows."""
        rows: list[tuple[float, float, float, float]] = []
        # Ticks before this frame see only the estimates before it.
        while self.next_tick < t:
            tick_hip = hip if live else self.hip_path(self.next_tick)
            _tick(self.fusion, self.next_tick, tick_hip, self.r_hip, rows)
            self.next_tick += self.tick_dt
        if self.feed is not None:
            self.feed.send(est, captured)
        # What the control process fuses: the same gate (quality, no estimator fallbacks).
        if admit(est, ADMIT_MIN_QUALITY):
            self.fusion.add(est)
        fused, fused_dp = _tick(self.fusion, t, hip, self.r_hip, rows)
        self.next_tick = max(self.next_tick, t + self.tick_dt)
        tick_rows = np.array(rows, dtype=np.float64).reshape(-1, len(TICK_COLUMNS))
        return fused, fused_dp, tick_rows

    def _frame(self, j: int, cam: Any, t: float) -> None:
        captured = time.monotonic()
        hip, robot, live = self._robot_now(t)
        pipe = self.pipes[j]
        t0 = time.perf_counter()
        if self.world_at is not None:
            self.world = self.world_at(t)
        world = self.world
        roi = cam.workspace_roi(hip, pipe.config.crop)
        depth = cam.render(world, t, occluders=robot, roi=roi)
        render_ms = 1e3 * (time.perf_counter() - t0)
        est = pipe.process_depth(depth, hip, exclude=robot)
        cut = None
        if self.recording is not None:
            cut = _cut(depth, hip, robot, est, pipe.config.crop, self.recording)
        context = self.twins[j].render(world, t, occluders=robot).points_world()
        context = context.astype(np.float32)
        truth = world.ground_truth(hip, t)
        fused, fused_dp, tick_rows = self._fuse(est, captured, t, hip, live)
        dp, err, nerr, row = _frame_row(j, t, est, fused, truth, hip, self.r_hip)
        # Read back what the pipelines and the fusion hold: the window shows that, not the
        # request (so a test of "the slider changed the pipeline" checks the pipeline).
        held = LiveConfig(perception=self.pipes[0].config, fusion=self.fusion.config)
        self.conn.send(
            FramePacket(
                camera=j,
                t=t,
                captured=captured,
                hip=hip,
                robot=robot,
                estimate=_estimate_fields(est),
                context=context,
                render_ms=render_ms,
                d_proj_m=dp,
                error_mm=err,
                normal_error_deg=nerr,
                fused=fused,
                fused_d_proj_m=fused_dp,
                truth=truth,
                body_offsets=tuple(b.displacement(t) for b in world.bodies),
                frame_row=row,
                tick_rows=tick_rows,
                config=held if self.version != self.sent_version else None,
                config_version=self.version,
                record=cut,
            )
        )
        self.sent_version = self.version


def _frame_row(
    j: int,
    t: float,
    est: SurfaceEstimate,
    fused: FusedSurface,
    truth: GroundTruth,
    hip: FloatArray,
    r_hip: float,
) -> tuple[float, float, float, tuple[float, ...]]:
    """The frame's projected distance and errors against the truth, and its history row."""
    if est.valid:
        dp = est.d_proj(hip, r_hip)
        err = 1e3 * float(np.linalg.norm(est.centroid - truth.point))
        nerr = _angle_deg(est.normal, truth.normal)
    else:
        dp = err = nerr = math.nan
    fused_err = (
        1e3 * float(np.linalg.norm(fused.centroid - truth.point))
        if fused is not None and fused.valid
        else math.nan
    )
    stage = [float(est.stage_ms.get(s, math.nan)) for s in (*STAGES, "total")]
    row = (
        t,
        float(j),
        float(est.valid),
        1e3 * dp,
        1e3 * (truth.distance_m - r_hip),
        err,
        nerr,
        fused_err,
        *stage,
    )
    return dp, err, nerr, row


def _context_camera(cam: Any) -> Any:
    """The same camera binned by :data:`CONTEXT_STRIDE`: the scene around the workspace."""
    from hapticloud.core.sim.depth_camera import SimDepthCamera

    return SimDepthCamera(
        cam.name,
        cam.intrinsics,
        cam.pose_world_camera,
        cam.noise,
        decimation=CONTEXT_STRIDE,
    )


def _tick(
    fusion: SurfaceFusion,
    t: float,
    hip: FloatArray,
    r_hip: float,
    rows: list[tuple[float, float, float, float]],
) -> tuple[FusedSurface, float]:
    fused = fusion.sample(t)
    if fused.valid:
        dp = d_proj(fused.centroid, fused.normal, hip, r_hip)
        target = d_proj(fused.target_centroid, fused.target_normal, hip, r_hip)
    else:
        dp = target = math.nan
    rows.append((t, float(fused.valid), 1e3 * dp, 1e3 * target))
    return fused, dp
