"""The simulated live source: sim cameras -> perception -> fusion, off the GUI, as frozen snapshots.

Who runs what
-------------
* A **worker** (:func:`run_worker`) owns every object of the data path: the simulated world, one
  :class:`~hapticloud.core.perception.CameraPipeline` per camera and the
  :class:`~hapticloud.core.fusion.SurfaceFusion`. It renders each camera at 30 Hz (interleaved),
  runs perception, adds the estimate to the fusion, samples the fusion at the control rate
  (800 Hz) between frames, and sends one small packet per camera frame down a pipe.
* By default the worker is a separate **process**, so that it never shares a GIL with the GUI:
  VTK's paint holds the GIL for most of its ~20 ms (a spinning Python thread kept 22 % of its
  speed during a paint), and with the worker on a thread the GUI's own Python work took twice as
  long (plot update 6.1 ms instead of 3 ms, whole window, same load) and the view rate dropped
  (13 instead of 20 fps), while a crash or stall of the worker would take the window with it.
  The real session's control loop needs the same separation. ``in_process=True`` runs the same
  function on a thread (debugging, profiling).
* A **receiver** thread in the GUI process turns packets into immutable :class:`Snapshot` objects
  numbered by ``seq`` (it keeps the history rings the plots read) and publishes the newest by
  rebinding one attribute, atomic in CPython. The GUI pulls :meth:`LiveSource.latest` on its own
  timer at display rate and drops a snapshot whose ``seq`` it has shown: nothing at camera or
  control rate goes through Qt signals, and the worker never waits for the GUI.

Requests go the other way: :meth:`LiveSource.request_config` queues a validated
:class:`LiveConfig` with a version number (the worker applies the newest one at the start of its
next frame and reports the version it applied); :meth:`LiveSource.emergency_stop` sets an event
the worker checks while pacing and between frames.

No Qt here: the hardware layer's session can implement :class:`SnapshotSource` with the same
snapshot types, and the window shows it unchanged.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
import multiprocessing as mp
import queue
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from hapticloud.core.config import StageConfig, nested
from hapticloud.core.control import ControllerConfig
from hapticloud.core.errors import ConfigError
from hapticloud.core.fusion import FusedSurface, FusionConfig, SurfaceFusion
from hapticloud.core.geometry.primitives import Box, Capsule, Primitive, Sphere
from hapticloud.core.haptics import d_proj
from hapticloud.core.loop import HapticsConfig, admit
from hapticloud.core.perception import STAGES, CameraPipeline, PerceptionConfig, SurfaceEstimate
from hapticloud.core.scene.schema import CameraSpec
from hapticloud.core.sim import GroundTruth, SimScene, demo_scene, end_effector
from hapticloud.core.studies.demo import CAMERA_RATE_HZ, DEMO_HANDLE_DIRECTION, hip_at
from hapticloud.core.studies.perception import R_HIP_M
from hapticloud.core.validation import read_only_copy
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: The scenes' default estimate gate (``cameras[i].min_quality``), as the control process uses.
ADMIT_MIN_QUALITY = CameraSpec().min_quality
#: Rate at which the fusion is sampled between camera frames (the haptic control rate).
CONTROL_RATE_HZ = 800.0
#: Seconds of history carried in every snapshot for the live plots.
HISTORY_S = 10.0
#: Every n-th pixel (both directions) of a frame is kept as that camera's scene cloud: enough to
#: show what the crop removed (~5k points per camera), small enough to send at 60 frames/s. It is
#: rendered by a twin camera binned by this factor: perception's camera renders only the pixels
#: of the workspace sphere (what stage A reads), a 64th of the rays goes to the picture around it.
CONTEXT_STRIDE = 8
#: Chord tolerance of the display meshes of the simulator's bodies (m). The ray-casting meshes
#: (0.1 mm, 176k vertices for the demo) are far too heavy to draw at 30 Hz in software GL.
DISPLAY_MESH_TOLERANCE_M = 0.002
#: Behind real time by more than this (s), the sim clock stops catching up and slows down
#: instead (shown as the real-time factor): no burst of frames after a stall.
MAX_LAG_S = 0.1

#: Per-frame history columns (one row per camera frame).
FRAME_COLUMNS = (
    "t",
    "camera",
    "valid",
    "d_proj_mm",
    "true_d_proj_mm",
    "error_mm",
    "normal_error_deg",
    "fused_error_mm",
    *(f"{stage}_ms" for stage in STAGES),
    "total_ms",
)
#: Per-control-tick history columns (CONTROL_RATE_HZ rows per second).
TICK_COLUMNS = ("t", "valid", "d_proj_mm", "target_d_proj_mm")


@dataclass(frozen=True)
class LiveConfig(StageConfig):
    """Every parameter the live view tunes, under one root so that a preset holds all tables.

    ``perception`` applies to every camera's pipeline; ``fusion`` to the shared fusion (a fusion
    change restarts the fusion's window: :class:`SurfaceFusion` has no in-place reconfiguration)
    and to the control process's fusion; ``haptics`` to the control process's haptic tick and
    ``controller`` to its hierarchical controller (only while the session is not enabled); the
    worker ignores both.
    """

    perception: PerceptionConfig = nested(PerceptionConfig)
    fusion: FusionConfig = nested(FusionConfig)
    haptics: HapticsConfig = nested(HapticsConfig)
    controller: ControllerConfig = nested(ControllerConfig)


class SourceState(enum.Enum):
    """Lifecycle of a source, as the window shows it."""

    STARTING = "starting"
    RUNNING = "running"
    STOPPED = "stopped"
    FAILED = "failed"


# ----- what the window reads ----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class BodyMesh:
    """Display mesh of one simulated body in its rest pose (m); ``faces`` are triangles."""

    name: str
    part: str
    vertices: FloatArray
    faces: NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class CameraInfo:
    """Where a camera is: optical centre and viewing axis in the world frame."""

    name: str
    origin: FloatArray
    axis: FloatArray


@dataclass(frozen=True, slots=True)
class SceneGeometry:
    """What does not change while a source runs: built into actors once by the view.

    ``robot_shapes`` names the kind (``"sphere"``, ``"capsule"``, ``"box"``) of each primitive of
    :attr:`Snapshot.robot`, in order: their number and kinds are fixed for a source.
    """

    name: str
    cameras: tuple[CameraInfo, ...]
    bodies: tuple[BodyMesh, ...]
    r_hip_m: float
    robot_shapes: tuple[str, ...] = ()
    description: str = ""


@dataclass(frozen=True, slots=True)
class CameraFrame:
    """One camera's newest frame as shown: its estimate, its scene cloud and its errors.

    ``context`` is the frame decimated by :data:`CONTEXT_STRIDE` (float32, world, m): what the
    crop removed is shown from it. ``error_mm`` / ``normal_error_deg`` compare the estimate with
    the simulator's truth (NaN when invalid or without truth); ``rate_hz`` is the camera's measured
    frame rate (wall clock) and ``render_ms`` what the simulated camera took.
    """

    name: str
    estimate: SurfaceEstimate
    context: NDArray[np.float32]
    render_ms: float
    rate_hz: float
    d_proj_m: float
    error_mm: float
    normal_error_deg: float


@dataclass(frozen=True, slots=True)
class History:
    """The last :data:`HISTORY_S` seconds, oldest first, as read-only arrays.

    ``frames`` has one row per camera frame with :data:`FRAME_COLUMNS` (``camera`` is the index
    into the scene's cameras); ``ticks`` one row per control tick with :data:`TICK_COLUMNS`.
    """

    frames: FloatArray
    ticks: FloatArray

    def frame(self, column: str) -> FloatArray:
        return self.frames[:, FRAME_COLUMNS.index(column)]

    def tick(self, column: str) -> FloatArray:
        return self.ticks[:, TICK_COLUMNS.index(column)]


@dataclass(frozen=True, slots=True)
class Snapshot:
    """Everything the window shows at one instant; immutable, numbered by ``seq``.

    ``t`` is the source's clock (s; simulation time here); ``captured`` and ``published`` are
    :func:`time.monotonic` times (system-wide, comparable across processes) at which the newest
    frame was taken and the snapshot was published: the window measures frame-to-screen latency
    from ``captured``. ``truth`` and ``body_offsets`` exist only in simulation. ``config`` is the
    configuration the pipelines held for this frame (read back from them) and ``config_version``
    the request it answers (0: the initial one).
    """

    seq: int
    t: float
    published: float
    captured: float
    state: SourceState
    message: str
    hip: FloatArray
    robot: tuple[Primitive, ...]
    cameras: tuple[CameraFrame, ...]
    fused: FusedSurface | None
    fused_d_proj_m: float
    truth: GroundTruth | None
    body_offsets: tuple[FloatArray, ...]
    config: LiveConfig
    config_version: int
    real_time_factor: float
    history: History


class SnapshotSource(Protocol):
    """What the window needs from a source (the simulated one now, the session later)."""

    @property
    def geometry(self) -> SceneGeometry: ...

    @property
    def state(self) -> SourceState: ...

    def start(self) -> None: ...

    def latest(self) -> Snapshot | None: ...

    def request_config(self, config: LiveConfig) -> int: ...

    def emergency_stop(self, reason: str) -> None: ...

    def close(self, timeout_s: float = 2.0) -> None: ...


# ----- scenes -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SimSettings:
    """What the worker runs (picklable: the worker process builds the scene from its name).

    ``speed`` is simulation time per wall time; ``decimation`` divides the cameras' resolution
    (1: 848x480 like the paper's D435s; 2: 424x240, about 4x cheaper to simulate).
    """

    scene: str = "demo"
    speed: float = 1.0
    decimation: int = 1
    r_hip_m: float = R_HIP_M
    handle_direction: tuple[float, float, float] = DEMO_HANDLE_DIRECTION

    def __post_init__(self) -> None:
        scene_spec(self.scene)  # a one-line ConfigError for an unknown scene or a bad file
        if not (math.isfinite(self.speed) and 0 < self.speed <= 10):
            raise ConfigError(f"speed = {self.speed}: must be in (0, 10]")
        if self.decimation not in (1, 2, 4):
            raise ConfigError(f"decimation = {self.decimation}: must be 1, 2 or 4")


@dataclass(frozen=True)
class SceneSpec:
    """A built-in simulated scene: how to build it and how its HIP moves."""

    build: Callable[..., SimScene]
    hip_path: Callable[[float], FloatArray]
    description: str
    #: The world at time ``t`` (s) for scenes whose bodies move on a schedule (scene files);
    #: ``None``: ``build(...).world`` moves by itself.
    world_at: Callable[[float], Any] | None = None


#: Built-in scenes by name; any other name is a scene file or a shipped scene of
#: ``assets/scenes/`` (:func:`scene_spec`).
SCENES: dict[str, SceneSpec] = {
    # The perception-only demo (--no-session): the hand reaches from the chest to the face on
    # its own. With a session the window shows the session's own scene file (one world for the
    # cameras, the truth and the control process: the built-in one stood 18 cm to the side).
    "demo-path": SceneSpec(
        demo_scene, hip_at, "seated patient, hand reaching from chest to face (no session)"
    ),
}


def scene_spec(name: str) -> SceneSpec:
    """The built-in scene ``name``, or one made from a scene file (``core.scene``): its bodies
    at their poses at t = 0 and its simulated D435s; without a session its HIP stays at the
    scene's ``hip0`` (a session moves it). Raises a one-line ConfigError for a bad name or file.
    """
    spec = SCENES.get(name)
    return spec if spec is not None else _file_scene_spec(name)


@functools.lru_cache(maxsize=8)
def _file_scene_spec(name: str) -> SceneSpec:
    from hapticloud.core.scene import load_scene

    try:
        loaded = load_scene(name)
    except ConfigError as err:
        builtin = ", ".join(SCENES)
        raise ConfigError(f"{err} (built-in scenes: {builtin}; or a scene file)") from None

    @functools.lru_cache(maxsize=4)
    def build(decimation: int = 1) -> SimScene:
        from hapticloud.core.sim.closed_loop import ClosedLoopSim

        over = {f"cameras.{c.name}.decimation": decimation for c in loaded.cameras}
        sim = ClosedLoopSim(loaded.with_overrides(over) if decimation > 1 else loaded)
        cams = tuple(c.camera for c in sim.cameras if c.camera is not None)
        world = sim.world.at(0.0)
        if not cams or world is None:
            raise ConfigError(
                f"scene {name!r}: the app needs bodies and simulated D435 cameras to show "
                "(oracle cameras render nothing)"
            )
        return SimScene(
            name=loaded.config.scene.name,
            world=world,
            cameras=cams,
            description=loaded.config.scene.description,
        )

    @functools.lru_cache(maxsize=1)
    def sim() -> Any:
        from hapticloud.core.sim.closed_loop import ClosedLoopSim

        return ClosedLoopSim(loaded)

    def hip_path(t: float) -> FloatArray:
        return read_only_copy(sim().hip0)

    def world_at(t: float) -> Any:
        # The scene's schedule (start, duration) as the closed loop runs it: the moving
        # surface moves in the view and in the simulated cameras too.
        return sim().world.at(t)

    moving = any(np.any(b.velocity_mps) for b in loaded.bodies) or loaded.has_surface
    return SceneSpec(build, hip_path, loaded.config.scene.description, world_at if moving else None)


def build_scene(settings: SimSettings) -> SimScene:
    return scene_spec(settings.scene).build(decimation=settings.decimation)


def robot_at(settings: SimSettings, hip: FloatArray) -> tuple[Primitive, ...]:
    """The robot's primitives the cameras see for a HIP (the demo: ball + handle)."""
    return tuple(end_effector(hip, np.asarray(settings.handle_direction, dtype=np.float64)))


def _shape_kind(prim: Primitive) -> str:
    return {Sphere: "sphere", Capsule: "capsule", Box: "box"}[type(prim)]


def scene_geometry(settings: SimSettings, scene: SimScene | None = None) -> SceneGeometry:
    """The static part of a simulated scene, with display-weight meshes."""
    scene = build_scene(settings) if scene is None else scene
    cameras = tuple(
        CameraInfo(cam.name, np.array(cam.origin_world), np.array(cam.axis_world))
        for cam in scene.cameras
    )
    bodies = tuple(
        BodyMesh(body.name, body.part, *body.rest_mesh_arrays(DISPLAY_MESH_TOLERANCE_M))
        for body in scene.world.bodies
    )
    robot = robot_at(settings, scene_spec(settings.scene).hip_path(0.0))
    shapes = tuple(_shape_kind(p) for p in robot)
    # Slots for the exoskeleton's links once a session drives the robot (session_robot): the
    # ball, then one capsule per link; unused slots are hidden.
    n_links = len(_link_model().capsule_specs)
    shapes = shapes + ("capsule",) * max(0, 1 + n_links - len(shapes))
    return SceneGeometry(scene.name, cameras, bodies, settings.r_hip_m, shapes, scene.description)


_LINK_MODEL: list[Any] = []


def _link_model() -> Any:
    """The robot model (loaded once per process) whose link capsules are drawn and occlude."""
    if not _LINK_MODEL:
        from hapticloud.core.robot import RobotModel

        _LINK_MODEL.append(RobotModel.load())
    return _LINK_MODEL[0]


def session_robot(hip: FloatArray, q: FloatArray) -> tuple[Primitive, ...]:
    """The robot as a session moves it: the end-effector ball at the HIP and every link of the
    exoskeleton (with the patient's strapped-in arm) at ``q``, as the closed-loop simulator
    renders and crops it."""
    ball = end_effector(hip, np.asarray(DEMO_HANDLE_DIRECTION, dtype=np.float64))[0]
    return (ball, *_link_model().link_capsules(q))


# ----- the worker (process or thread) -------------------------------------------------------------


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
class _Packet:
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
class _End:
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
    """Run the simulated data path until ``stop`` is set; one :class:`_Packet` per frame.

    ``conn`` is the sending end of a pipe, ``requests`` a queue of ``(version, LiveConfig)``,
    ``stop`` an event. Runs in a worker process (or thread); everything it builds is its own.
    With ``session`` the HIP comes from the control process and every estimate goes to it.
    """
    feed = None
    if session is not None:
        try:
            feed = _SessionFeed(session)
        except (OSError, ValueError):
            feed = None  # the session is already gone: perception alone
    try:
        _worker_loop(settings, config, conn, requests, stop, feed)
    except (BrokenPipeError, EOFError, OSError):
        return  # the receiver is gone: nobody to tell
    except Exception as err:  # report, do not die silently
        last = traceback.format_exception_only(err)[-1].strip()
        try:
            conn.send(_End(SourceState.FAILED, f"source failed: {last}"))
        except OSError:
            pass
        return
    finally:
        if feed is not None:
            feed.close()
    try:
        conn.send(_End(SourceState.STOPPED, "stopped"))
    except OSError:
        pass


def _worker_loop(
    settings: SimSettings,
    config: LiveConfig,
    conn: Any,
    requests: Any,
    stop: Any,
    feed: _SessionFeed | None = None,
) -> None:
    from hapticloud.core.threads import settle_numerics

    settle_numerics(1)
    scene = build_scene(settings)
    world, cameras = scene.world, scene.cameras
    spec = scene_spec(settings.scene)
    hip_path, world_at = spec.hip_path, spec.world_at
    r_hip = settings.r_hip_m
    pipes = [CameraPipeline(config.perception, camera=c.name) for c in cameras]
    twins = [_context_camera(c) for c in cameras]
    fusion = SurfaceFusion(config.fusion)
    period = 1.0 / CAMERA_RATE_HZ
    tick_dt = 1.0 / CONTROL_RATE_HZ
    version, sent_version = 0, -1
    recording = None  # a RecordConfig while the app records
    next_tick = 0.0
    wall0 = time.monotonic()
    k = 0
    while not stop.is_set():
        for j, cam in enumerate(cameras):
            # Interleaved like the demo: camera j fires j/n of a period after camera 0.
            t = k * period + j * period / len(cameras)
            delay = wall0 + t / settings.speed - time.monotonic()
            if delay > 0:
                if stop.wait(delay):
                    return
            elif delay < -MAX_LAG_S:
                wall0 = time.monotonic() - t / settings.speed
            if stop.is_set():
                return
            newest = None
            while True:  # drain: the newest request wins
                try:
                    item = requests.get_nowait()
                except queue.Empty:
                    break
                if isinstance(item, RecordRequest):
                    recording = item.record
                    continue
                if isinstance(item, SessionAttach):  # a session that came up after the start
                    if feed is not None:
                        feed.close()
                    try:
                        feed = _SessionFeed(item)
                    except (OSError, ValueError):
                        feed = None
                else:
                    newest = item
            if newest is not None:
                version, requested = newest
                if requested.perception != config.perception:
                    for pipe in pipes:
                        pipe.configure(requested.perception)
                if requested.fusion != config.fusion:
                    fusion = SurfaceFusion(requested.fusion)
                    next_tick = t
                config = requested

            captured = time.monotonic()
            live = feed.state() if feed is not None else None
            live_hip = None if live is None else live[0]
            if live is None:
                hip = np.asarray(hip_path(t), dtype=np.float64)
                robot = robot_at(settings, hip)
            else:
                hip = live_hip
                robot = session_robot(*live)
            t0 = time.perf_counter()
            if world_at is not None:
                world = world_at(t)
            roi = cam.workspace_roi(hip, pipes[j].config.crop)
            depth = cam.render(world, t, occluders=robot, roi=roi)
            render_ms = 1e3 * (time.perf_counter() - t0)
            est = pipes[j].process_depth(depth, hip, exclude=robot)
            cut = None
            if recording is not None:
                cut = _cut(depth, hip, robot, est, pipes[j].config.crop, recording)
            context = twins[j].render(world, t, occluders=robot).points_world()
            context = context.astype(np.float32)
            truth = world.ground_truth(hip, t)

            # Ticks before this frame see only the estimates before it.
            rows: list[tuple[float, float, float, float]] = []
            fused: FusedSurface | None = None
            fused_dp = math.nan
            while next_tick < t:
                tick_hip = hip if live_hip is not None else hip_path(next_tick)
                fused, fused_dp = _tick(fusion, next_tick, tick_hip, r_hip, rows)
                next_tick += tick_dt
            if feed is not None:
                feed.send(est, captured)
            # What the control process fuses: the same gate (quality, no estimator fallbacks).
            if admit(est, ADMIT_MIN_QUALITY):
                fusion.add(est)
            fused, fused_dp = _tick(fusion, t, hip, r_hip, rows)
            next_tick = max(next_tick, t + tick_dt)

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
            # Read back what the pipelines and the fusion hold: the window shows that, not the
            # request (so a test of "the slider changed the pipeline" checks the pipeline).
            held = LiveConfig(perception=pipes[0].config, fusion=fusion.config)
            conn.send(
                _Packet(
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
                    tick_rows=np.array(rows, dtype=np.float64).reshape(-1, len(TICK_COLUMNS)),
                    config=held if version != sent_version else None,
                    config_version=version,
                    record=cut,
                )
            )
            sent_version = version
        k += 1


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


# ----- the GUI process's side ---------------------------------------------------------------------


class _Ring:
    """Fixed-capacity table of float rows; :meth:`ordered` copies it out oldest first."""

    def __init__(self, capacity: int, n_columns: int) -> None:
        self._data = np.full((capacity, n_columns), np.nan)
        self._next = 0
        self._full = False

    def extend(self, rows: FloatArray) -> None:
        for row in np.atleast_2d(rows):
            self._data[self._next] = row
            self._next += 1
            if self._next == len(self._data):
                self._next = 0
                self._full = True

    def ordered(self) -> FloatArray:
        if self._full:
            out = np.concatenate((self._data[self._next :], self._data[: self._next]))
        else:
            out = self._data[: self._next].copy()
        out.setflags(write=False)
        return out


@dataclass
class _Receiver:
    """State the receiver thread keeps to compose snapshots (touched by that thread only)."""

    n_cameras: int
    frames: _Ring = field(init=False)
    ticks: _Ring = field(init=False)
    newest: dict[int, CameraFrame] = field(default_factory=dict)
    arrivals: dict[int, deque[float]] = field(default_factory=dict)
    clock: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=61))
    config: LiveConfig | None = None

    def __post_init__(self) -> None:
        rows = int(HISTORY_S * CAMERA_RATE_HZ) * self.n_cameras + 1
        self.frames = _Ring(rows, len(FRAME_COLUMNS))
        self.ticks = _Ring(int(HISTORY_S * CONTROL_RATE_HZ) + 1, len(TICK_COLUMNS))
        self.arrivals = {i: deque(maxlen=31) for i in range(self.n_cameras)}


class LiveSource:
    """Runs a simulated scene live off the GUI thread and publishes :class:`Snapshot` objects.

    Parameters
    ----------
    settings
        Scene, speed and camera resolution.
    config
        Initial parameters (validated: a built :class:`LiveConfig`).
    in_process
        Run the worker on a thread of this process instead of its own process (debugging; the GUI
        slows it down, see the module docstring).
    session
        A running control process to feed (:class:`SessionAttach`): the HIP then comes from the
        robot's shared state and every estimate goes to the loop's fusion.

    Example
    -------
    >>> src = LiveSource(SimSettings(scene="demo"))
    >>> src.start()
    >>> # ... the GUI polls src.latest() on a timer ...
    >>> src.close()
    """

    def __init__(
        self,
        settings: SimSettings | None = None,
        config: LiveConfig | None = None,
        *,
        in_process: bool = False,
        session: SessionAttach | None = None,
    ) -> None:
        self.settings = SimSettings() if settings is None else settings
        self.session = session
        self._config = LiveConfig() if config is None else config
        if not isinstance(self._config, LiveConfig):
            raise ConfigError(f"config: expected a LiveConfig, got {type(config).__name__}")
        self._geometry = scene_geometry(self.settings)
        self._in_process = in_process
        ctx = mp.get_context("spawn")  # never fork a process that runs Qt threads
        self._ctx = ctx
        self._stop = ctx.Event()
        self._requests = ctx.Queue()
        self._version = 0
        self._latest: Snapshot | None = None
        self._state = SourceState.STARTING
        self._message = ""
        self._worker: Any = None
        self._receiver: threading.Thread | None = None
        self._seq = 0
        self._record_sink: Any = None

    # ----- the window's side -------------------------------------------------------------------
    @property
    def geometry(self) -> SceneGeometry:
        return self._geometry

    @property
    def state(self) -> SourceState:
        return self._state

    @property
    def message(self) -> str:
        return self._message

    @property
    def requested_config(self) -> LiveConfig:
        """The newest configuration asked for (the worker applies it at its next frame)."""
        return self._config

    def start(self) -> None:
        """Start the worker and the receiver (once)."""
        if self._worker is not None:
            raise RuntimeError("LiveSource.start: already started")
        recv_end, send_end = self._ctx.Pipe(duplex=False)
        args = (self.settings, self._config, send_end, self._requests, self._stop, self.session)
        if self._in_process:
            self._worker = threading.Thread(
                target=run_worker, args=args, name="hapticloud-sim-worker", daemon=True
            )
        else:
            self._worker = self._ctx.Process(
                target=run_worker, args=args, name="hapticloud-sim-worker", daemon=True
            )
        self._worker.start()
        if not self._in_process:
            send_end.close()  # the child holds it; EOF reaches us when the child exits
        self._receiver = threading.Thread(
            target=self._receive, args=(recv_end,), name="hapticloud-snapshots", daemon=True
        )
        self._receiver.start()

    def attach_session(self, session: SessionAttach) -> None:
        """Feed a control process that came up after :meth:`start` (from the next frame on)."""
        self.session = session
        self._requests.put(session)

    def latest(self) -> Snapshot | None:
        """The newest snapshot (``None`` before the first frame); never blocks."""
        return self._latest

    def record_to(self, sink: Any, record: Any = None) -> None:
        """Record every frame shown from the next one on: the worker cuts it
        (:func:`~hapticloud.hardware.recording.recorder.cut_frame`, ``record`` or the default
        :class:`~hapticloud.core.recording.RecordConfig`) into the display's packet and the
        receiver hands it to ``sink.put_cut(capture time, cut)``; ``None`` stops."""
        from hapticloud.core.recording import RecordConfig

        self._record_sink = sink
        self._requests.put(RecordRequest(None if sink is None else record or RecordConfig()))

    def request_config(self, config: LiveConfig) -> int:
        """Use ``config`` from the next frame on; returns the request's version number.

        ``config`` is a built, hence validated, :class:`LiveConfig`: an invalid value is refused
        where it is typed (:meth:`StageConfig.replace_path`) and never gets this far.
        """
        if not isinstance(config, LiveConfig):
            raise ConfigError(f"config: expected a LiveConfig, got {type(config).__name__}")
        self._version += 1
        self._config = config
        self._requests.put((self._version, config))
        return self._version

    def emergency_stop(self, reason: str = "emergency stop") -> None:
        """Stop the simulation; returns at once (the worker ends within one frame)."""
        if not self._stop.is_set():
            self._message = reason
            self._stop.set()

    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop and wait for the worker (at most ``timeout_s``, then terminate it)."""
        self.emergency_stop(self._message or "closed")
        worker = self._worker
        if worker is not None:
            worker.join(timeout_s)
            if isinstance(worker, mp.process.BaseProcess) and worker.is_alive():
                worker.terminate()
                worker.join(1.0)
        if self._receiver is not None:
            self._receiver.join(timeout_s)
        self._requests.close()
        self._requests.join_thread()

    @property
    def alive(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    # ----- the receiver thread -----------------------------------------------------------------
    def _receive(self, conn: Any) -> None:
        state = _Receiver(len(self._geometry.cameras))
        end: _End | None = None
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                break
            if isinstance(msg, _End):
                end = msg
                break
            self._state = SourceState.RUNNING
            sink = self._record_sink
            if sink is not None and msg.record is not None:
                sink.put_cut(msg.captured, msg.record)
            self._latest = self._compose(state, msg)
        conn.close()
        if end is None:
            end = _End(SourceState.STOPPED if self._stop.is_set() else SourceState.FAILED, "")
        if end.state is SourceState.FAILED:
            self._message = end.message or "the worker ended unexpectedly"
        self._state = end.state
        last = self._latest
        if last is not None:
            self._seq += 1
            self._latest = dataclasses.replace(
                last,
                seq=self._seq,
                state=end.state,
                message=self._message or end.message,
                published=time.monotonic(),
            )

    def _compose(self, state: _Receiver, p: _Packet) -> Snapshot:
        now = time.monotonic()
        est = SurfaceEstimate(**p.estimate)
        stamps = state.arrivals[p.camera]
        stamps.append(now)
        rate = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 2 else math.nan
        state.newest[p.camera] = CameraFrame(
            name=est.camera,
            estimate=est,
            context=read_only_copy(p.context, np.float32),
            render_ms=p.render_ms,
            rate_hz=rate,
            d_proj_m=p.d_proj_m,
            error_mm=p.error_mm,
            normal_error_deg=p.normal_error_deg,
        )
        state.frames.extend(np.asarray(p.frame_row, dtype=np.float64))
        if len(p.tick_rows):
            state.ticks.extend(p.tick_rows)
        state.clock.append((now, p.t))
        if p.config is not None:
            state.config = p.config
        self._seq += 1
        (w0, s0), (w1, s1) = state.clock[0], state.clock[-1]
        rtf = (s1 - s0) / (w1 - w0) if len(state.clock) > 2 and w1 > w0 else math.nan
        return Snapshot(
            seq=self._seq,
            t=p.t,
            published=now,
            captured=p.captured,
            state=SourceState.RUNNING,
            message="",
            hip=read_only_copy(p.hip),
            robot=p.robot,
            cameras=tuple(state.newest[i] for i in sorted(state.newest)),
            fused=p.fused,
            fused_d_proj_m=p.fused_d_proj_m,
            truth=p.truth,
            body_offsets=tuple(read_only_copy(o) for o in p.body_offsets),
            config=state.config if state.config is not None else self._config,
            config_version=p.config_version,
            real_time_factor=rtf,
            history=History(state.frames.ordered(), state.ticks.ordered()),
        )
