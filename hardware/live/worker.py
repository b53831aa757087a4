"""The live worker: the app's cameras through the perception worker, one packet per camera frame.

The worker (:func:`run_worker`, run by :class:`~.source.LiveSource` in its own process or on a
thread) runs the one perception worker (:class:`~hapticloud.hardware.perception.PerceptionWorker`)
over the scene's simulated D435s: each camera a
:class:`~hapticloud.hardware.perception.RenderedChannel` (its workspace ROI rendered, then its
:class:`~hapticloud.core.perception.CameraPipeline`) at 30 Hz, interleaved; the robot they see
(the HIP for the crop, its ball and links as occluders) from the session's state block, or the
scene's scripted HIP path while there is no session (:class:`LiveRobot`). Each frame goes to
the control process's fusion (a :class:`~hapticloud.hardware.perception.ControlSink`, with a
session) and to the display (:class:`Display`: the display's own fusion sampled at the control
rate between frames, a low-resolution context cloud of the scene, the truth, and one small
:class:`FramePacket` down a pipe).

Time: one clock, the control loop's (:func:`time.monotonic`). A frame's scene time is the time
the robot was where the camera saw it (``(pose.t - start) * speed``) and the estimate the loop
fuses is stamped with that same ``pose.t``: the loop judges its age on its own clock. A frame
the machine cannot render in time is dropped (the camera's rate shows it), as a camera's driver
drops it; the cameras' clock never slows down. The simulated plant's own pace (the control
process's simulation clock) is the session's ``sim_time_factor``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import queue
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from hapticloud.core.fusion import FusedSurface, SurfaceFusion
from hapticloud.core.geometry.primitives import Primitive
from hapticloud.core.haptics import trusted_d_proj
from hapticloud.core.perception import STAGES, CameraPipeline, SurfaceEstimate
from hapticloud.core.scene.schema import CameraSpec
from hapticloud.core.sim import GroundTruth
from hapticloud.core.studies.demo import CAMERA_RATE_HZ
from numpy.typing import NDArray

from ..control.deadline import try_sched_fifo
from ..perception import (
    ChannelSpec,
    ControlSink,
    DisplaySink,
    Perceived,
    PerceptionWorker,
    RenderedChannel,
    RobotPose,
    StateBlockFeed,
)
from ..sources import open_source
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
#: Each camera's scene cloud is rendered and sent at most this often (s, scene time); frames in
#: between carry none and the receiver keeps the last. It is a picture of the room around the
#: workspace (its layer is off by default), not something perception or the truth reads: at
#: every frame it cost ~8 % of a core of the 2 (render, pickling and the receiver's copy).
CONTEXT_PERIOD_S = 0.2
#: ``SCHED_FIFO`` priority of the worker's frame loop: below the control loop's (80), above
#: every normal task. Its frames feed the control loop's estimate and frame watchdogs (0.1 s).
#: At ``nice`` -5 beside the GUI's software rendering on 2 cores, a frame that takes 3-5 ms
#: alone took 9-17 ms (up to 45 ms in the reaches): a normal task preempted by the control loop
#: waits on that CPU instead of moving to the other, and the surface was held 2-15 times a
#: minute. A real-time task is moved at once; it sleeps between frames (~30 % of one core).
#: Set once the worker is built (its start-up, ~1 s of scene building, runs at ``WORKER_NICE``).
WORKER_FIFO_PRIORITY = 40
#: ``nice`` value of the worker process while it builds, and for good where ``SCHED_FIFO`` is
#: refused (negative: ahead of the GUI, which gives way too: ``app.commands.app.GUI_NICE``),
#: set as is. Needs root (or CAP_SYS_NICE); refused, it keeps the GUI's.
WORKER_NICE = -5


@dataclass(frozen=True)
class SessionAttach:
    """What the worker needs to feed a running control process (picklable at spawn).

    ``estimates`` is :attr:`ControlProcess.estimate_connection` (the write end of its estimates
    pipe); ``state_block`` the name of its :class:`RobotStateBlock` (the robot's HIP and q, every
    tick) and ``n_joints`` its layout. With a session, the cameras see the robot of the block
    instead of the scripted path, and every estimate goes to the loop.
    """

    estimates: Any
    state_block: str
    n_joints: int = 6


@dataclass(frozen=True)
class ContextRequest:
    """Ask the worker to render and send each camera's scene cloud (``on``), or not. The worker
    renders them until told otherwise; the window's layer is off by default, and the window asks
    before it starts the source (the request is queued ahead of the worker's first frame)."""

    on: bool


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
    mapping proxy does not pickle) and are rebuilt, frozen, on the receiving side.

    ``t`` is the frame's scene time (the estimate's ``t`` too), ``captured`` the
    :func:`time.monotonic` time the robot was where the camera saw it; ``render_ms`` what
    rendering took (the frame's perception time less the pipeline's)."""

    camera: int
    t: float
    captured: float
    hip: FloatArray
    robot: tuple[Primitive, ...]
    estimate: dict[str, Any]
    context: NDArray[np.float32] | None  # None: unchanged since this camera's last one
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
    own_process: bool = False,
) -> None:
    """Run the simulated data path until ``stop`` is set; one :class:`FramePacket` per frame.

    ``conn`` is the sending end of a pipe, ``requests`` a queue of ``(version, LiveConfig)``,
    :class:`RecordRequest`, :class:`ContextRequest` and :class:`SessionAttach`, ``stop`` an
    event. Runs in a worker process (``own_process``: its frame loop then takes
    ``SCHED_FIFO`` :data:`WORKER_FIFO_PRIORITY` where permitted) or on a thread (it shares the
    window's interpreter lock: ``nice`` only); everything it builds is its own. With
    ``session`` the cameras see the control process's robot and every estimate goes to it.
    """
    worker: _Worker | None = None
    try:
        os.setpriority(os.PRIO_PROCESS, 0, WORKER_NICE)
    except OSError:
        pass  # not permitted: the priority it was started with
    try:
        worker = _Worker(settings, config, conn, requests, stop)
        if session is not None:
            worker.attach(session)
        if own_process:
            try_sched_fifo(WORKER_FIFO_PRIORITY, fallback_nice=WORKER_NICE)
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
        if worker is not None:
            worker.perception.close()
    try:
        conn.send(WorkerEnded(SourceState.STOPPED, "stopped"))
    except OSError:
        pass


class LiveRobot:
    """The robot the app's cameras see (a :class:`~hapticloud.hardware.perception.RobotFeed`):
    the session's (its state block: HIP and joints, stamped with the tick that wrote them) while
    it has a state, else the scene's scripted HIP path at the scene time of now (no joints).

    ``scene_time`` maps a clock time to scene time (the perception worker's, once built).
    """

    def __init__(
        self,
        hip_path: Callable[[float], Any],
        scene_time: Callable[[float], float],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.hip_path = hip_path
        self.scene_time = scene_time
        self._clock = clock
        self.session: StateBlockFeed | None = None

    def attach(self, block_name: str, n_joints: int) -> None:
        """Follow the session's robot from now on (its state block ``block_name``)."""
        self.close()
        self.session = StateBlockFeed(block_name, n_joints)

    def read(self) -> RobotPose:
        if self.session is not None:
            pose = self.session.read()
            if pose is not None:
                return pose
        now = self._clock()
        hip = np.asarray(self.hip_path(self.scene_time(now)), dtype=np.float64)
        return RobotPose(now, hip, None)

    def close(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None


class _Worker:
    """The perception worker over the app's cameras, the display sink and the requests."""

    def __init__(
        self,
        settings: SimSettings,
        config: LiveConfig,
        conn: Any,
        requests: Any,
        stop: Any,
    ) -> None:
        from hapticloud.core.threads import settle_numerics

        settle_numerics(1)
        scene = build_scene(settings)
        spec = scene_spec(settings.scene)
        self.settings, self.requests, self.stop = settings, requests, stop
        cameras = scene.cameras
        world = spec.world_at if spec.world_at is not None else scene.world
        channels = [_channel(cam, j, len(cameras), world, config) for j, cam in enumerate(cameras)]
        self.display = Display(settings, config, conn, scene.world, spec, channels)
        self.robot = LiveRobot(spec.hip_path, lambda t: 0.0)
        self.perception = PerceptionWorker(
            channels,
            self.robot,
            [DisplaySink(self.display.put)],
            occluders=self._occluders,
            time_scale=settings.speed,
            catch_up=True,  # a late render is not a late exposure: render it now
        )
        self.robot.scene_time = self.perception.scene_time
        self.control: ControlSink | None = None

    def _occluders(self, pose: RobotPose) -> tuple[Primitive, ...]:
        """The session's robot (ball + links), or the scripted one (ball + handle)."""
        if pose.q is None:
            return robot_at(self.settings, pose.hip)
        return session_robot(pose.hip, pose.q)

    def attach(self, session: SessionAttach) -> None:
        """Feed the control process of ``session`` (its estimates first, then the display)."""
        if self.control is not None:
            self.perception.sinks.remove(self.control)
            self.control = None
        try:
            self.robot.attach(session.state_block, session.n_joints)
        except (OSError, ValueError):
            return  # the session is already gone: perception alone
        self.control = ControlSink(session.estimates, drop_when_full=True)
        self.perception.sinks.insert(0, self.control)

    def run(self) -> None:
        perception, stop = self.perception, self.stop
        perception.start()
        while not stop.is_set():
            self._apply_requests()
            wake = perception.step()
            if stop.wait(max(0.0, wake - time.monotonic())):
                return

    def _apply_requests(self) -> None:
        newest = None
        while True:  # drain: the newest request wins
            try:
                item = self.requests.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, RecordRequest):
                self.display.recording = item.record
            elif isinstance(item, ContextRequest):
                self.display.context_wanted = item.on
            elif isinstance(item, SessionAttach):  # a session that came up after the start
                self.attach(item)
            else:
                newest = item
        if newest is not None:
            now = self.perception.scene_time(time.monotonic())
            self.display.configure(*newest, now)


def _channel(cam: Any, j: int, n: int, world: Any, config: LiveConfig) -> RenderedChannel:
    """Camera ``j`` of ``n`` as the worker's channel: 30 Hz, interleaved like the demo (camera
    j fires j/n of a period after camera 0), gated like the control process gates it."""
    spec = ChannelSpec(
        cam.name,
        rate_hz=CAMERA_RATE_HZ,
        phase_s=j / (n * CAMERA_RATE_HZ),
        min_quality=ADMIT_MIN_QUALITY,
    )
    source = open_source(
        "simulated",
        camera=cam,
        world=world,
        rate_hz=spec.rate_hz,
        phase_s=spec.phase_s,
        realtime=False,
    )
    return RenderedChannel(spec, source, CameraPipeline(config.perception, camera=cam.name))


class Display:
    """What the window shows of each perceived frame (a
    :class:`~hapticloud.hardware.perception.DisplaySink`'s callback, in the worker's thread):
    the display's own fusion sampled at the control rate up to the frame, the frame's context
    cloud, the truth, its errors, and the :class:`FramePacket` sent down ``conn``."""

    def __init__(
        self,
        settings: SimSettings,
        config: LiveConfig,
        conn: Any,
        world: Any,
        spec: Any,
        channels: Sequence[RenderedChannel],
    ) -> None:
        self.conn, self.config = conn, config
        self.world, self.world_at, self.hip_path = world, spec.world_at, spec.hip_path
        self.r_hip = settings.r_hip_m
        self.channels = list(channels)
        self.index = {c.name: j for j, c in enumerate(self.channels)}
        self.twins = [_context_camera(c.source.camera) for c in self.channels]
        self.context_t = [-math.inf] * len(self.channels)  # scene time of each one's last
        self.fusion = SurfaceFusion(config.fusion)
        self.tick_dt = 1.0 / CONTROL_RATE_HZ
        self.version, self.sent_version = 0, -1
        self.recording: Any = None  # a RecordConfig while the app records
        #: Render the scene cloud (until a :class:`ContextRequest` says the window hides it).
        self.context_wanted = True
        self.next_tick = 0.0

    def configure(self, version: int, requested: LiveConfig, t: float) -> None:
        """Use ``requested`` from the next frame on (scene time ``t`` now)."""
        self.version = version
        if requested.perception != self.config.perception:
            for channel in self.channels:
                channel.pipeline.configure(requested.perception)
        if requested.fusion != self.config.fusion:
            self.fusion = SurfaceFusion(requested.fusion)
            self.next_tick = t
        self.config = requested

    def put(self, item: Perceived) -> None:
        j, t, hip = self.index[item.camera], item.t_scene, item.hip
        robot = tuple(item.occluders)
        # The display runs on scene time: its fusion, history and status read the estimate so.
        est = dataclasses.replace(item.estimate, t=t)
        if self.world_at is not None:
            self.world = self.world_at(t)
        world = self.world
        cut = None
        if self.recording is not None:
            crop = self.channels[j].crop
            cut = _cut(item.frame, hip, robot, est, crop, self.recording)
        context = None
        if self.context_wanted and not 0.0 <= t - self.context_t[j] < CONTEXT_PERIOD_S:
            # Due (or the clock went back), and shown: nobody reads it otherwise.
            context = self.twins[j].render(world, t, occluders=robot).points_world()
            context = context.astype(np.float32)
            self.context_t[j] = t
        truth = world.ground_truth(hip, t)
        fused, fused_dp, tick_rows = self._fuse(est, item.admitted, t, hip, item.q is not None)
        dp, err, nerr, row = _frame_row(j, t, est, fused, truth, hip, self.r_hip)
        held = None
        if self.version != self.sent_version:
            # Read back what the pipelines and the fusion hold: the window shows that, not the
            # request (so a test of "the slider changed the pipeline" checks the pipeline).
            # Only on a change: building a LiveConfig validates every table (~2 ms).
            held = LiveConfig(
                perception=self.channels[0].pipeline.config, fusion=self.fusion.config
            )
        self.conn.send(
            FramePacket(
                camera=j,
                t=t,
                captured=item.captured,
                hip=hip,
                robot=robot,
                estimate=_estimate_fields(est),
                context=context,
                render_ms=item.perception_ms - float(est.stage_ms.get("total", 0.0)),
                d_proj_m=dp,
                error_mm=err,
                normal_error_deg=nerr,
                fused=fused,
                fused_d_proj_m=fused_dp,
                truth=truth,
                body_offsets=tuple(b.displacement(t) for b in world.bodies),
                frame_row=row,
                tick_rows=tick_rows,
                config=held,
                config_version=self.version,
                record=cut,
            )
        )
        self.sent_version = self.version

    def _fuse(
        self, est: SurfaceEstimate, admitted: bool, t: float, hip: FloatArray, live: bool
    ) -> tuple[FusedSurface, float, FloatArray]:
        """Sample the fusion at the control rate up to this frame, then add the frame's estimate
        (if the loop's gate admits it); the fused surface at ``t``, its projected distance and
        the ticks' history rows."""
        rows: list[tuple[float, float, float, float]] = []
        # Ticks before this frame see only the estimates before it.
        while self.next_tick < t:
            tick_hip = hip if live else np.asarray(self.hip_path(self.next_tick), dtype=np.float64)
            _tick(self.fusion, self.next_tick, tick_hip, self.r_hip, rows)
            self.next_tick += self.tick_dt
        if admitted:
            self.fusion.add(est)
        fused, fused_dp = _tick(self.fusion, t, hip, self.r_hip, rows)
        self.next_tick = max(self.next_tick, t + self.tick_dt)
        tick_rows = np.array(rows, dtype=np.float64).reshape(-1, len(TICK_COLUMNS))
        return fused, fused_dp, tick_rows


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
        # The fusion hands out float (3,) arrays with unit normals (checked there).
        dp = trusted_d_proj(fused.centroid, fused.normal, hip, r_hip)
        target = trusted_d_proj(fused.target_centroid, fused.target_normal, hip, r_hip)
    else:
        dp = target = math.nan
    rows.append((t, float(fused.valid), 1e3 * dp, 1e3 * target))
    return fused, dp
