"""A scene's parts, built in one place: robot, world, walls, cameras, perception, fusion, control.

Every entry point that runs a scene (``hapticloud run``, ``run --hardware``, ``bench loop``, the
app, the emulated arm) builds it here, so that they all see the same robot start, the same
world, the same cameras and the same controller. Each part has its own builder; :func:`assemble`
composes them in the order their inputs need::

    robot = build_robot(scene)
    q0 = initial_joints(scene, robot)          # the scene's q0, or IK to its hip0
    hip0 = robot.hip_position_at(q0)
    world = build_world(scene, hip0)           # the moving surface starts next to hip0
    walls = build_walls(scene)
    cameras = build_cameras(scene, hip0)       # aimed at hip0 unless they name a target;
                                               # a pipeline each (build_pipeline), oracles none
    fusion = build_fusion(scene, cameras)      # only with a camera
    controller = build_scene_controller(scene, robot, walls)
    loop = build_loop(scene, robot, controller, fusion, walls)
    patient = build_patient(scene, q0, hip0)   # only with a [patient] table
    check_start(...)                           # the HIP sphere must start outside every surface

Only what the scene declares is built: no cameras -> no pipeline, no fusion; no ``[patient]`` ->
no patient. The parts are live objects (the fusion, the tick, the cameras' frame counters keep
state): one :class:`Assembly` per run. Nothing here runs a clock, a thread or a device; the
closed-loop simulation (:class:`~hapticloud.core.sim.closed_loop.ClosedLoopSim`) adds the plant
and the run, the hardware layer adds the drives and the processes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..camera import CameraIntrinsics, DepthFrame, look_at
from ..control import HierarchicalController
from ..errors import ConfigError
from ..fusion import SurfaceFusion
from ..geometry import Capsule, rotation_between
from ..loop import HapticLoop, Wall, build_controller
from ..perception import CameraPipeline, SurfaceEstimate
from ..robot import RobotModel
from ..sim.bodies import Body, BoxBody, CapsuleBody, CylinderBody, EllipsoidBody, SphereBody
from ..sim.depth_camera import SimDepthCamera
from ..sim.exo import solve_hip_ik
from ..sim.patient import IntentScript, PatientArm, Waypoint, segment_time
from ..sim.scenes import PLACEMENT_YAW_DEG, placement_eye, rotation_xyz
from ..sim.world import SimWorld
from .loader import Scene
from .schema import BodySpec, CameraSpec

FloatArray = NDArray[np.float64]

#: What a camera hook receives for each rendered frame: ``(frame, hip, exclude, estimate)``.
FrameSink = Callable[[DepthFrame, FloatArray, list[Capsule], SurfaceEstimate], None]


class InfeasibleSceneError(ConfigError):
    """The scene cannot be run as declared (unreachable start, HIP starting inside a body)."""


# ----- the world with moving bodies --------------------------------------------------------------
@dataclass(frozen=True)
class Motion:
    """Constant velocity (m/s) from ``start_s`` for ``duration_s`` (0: forever), else at rest."""

    velocity: FloatArray
    start_s: float = 0.0
    duration_s: float = 0.0

    def displacement(self, t: float) -> FloatArray:
        """Translation from the rest pose at time ``t`` (s), m."""
        moving = t - self.start_s
        if moving <= 0.0:
            return np.zeros(3)
        if self.duration_s > 0.0:
            moving = min(moving, self.duration_s)
        return self.velocity * moving

    def velocity_at(self, t: float) -> FloatArray:
        """Velocity (m/s) at time ``t``."""
        moving = t - self.start_s
        if moving < 0.0 or (self.duration_s > 0.0 and moving >= self.duration_s):
            return np.zeros(3)
        return self.velocity

    @property
    def is_static(self) -> bool:
        return not np.any(self.velocity)


def body_from_spec(spec: BodySpec) -> Body:
    """The analytic body of a ``[[bodies]]`` entry, at rest (motion applied separately)."""
    rot = rotation_xyz(*spec.rotation_deg)
    common = {"name": spec.name, "part": spec.part}
    if spec.type == "sphere":
        return SphereBody(**common, center=spec.center_m, radius_m=spec.radius_m)
    if spec.type == "ellipsoid":
        return EllipsoidBody(
            **common, center=spec.center_m, semi_axes_m=spec.semi_axes_m, rotation=rot
        )
    if spec.type == "capsule":
        return CapsuleBody(**common, a=spec.a_m, b=spec.b_m, radius_m=spec.radius_m)
    if spec.type == "cylinder":
        return CylinderBody(**common, a=spec.a_m, b=spec.b_m, radius_m=spec.radius_m)
    return BoxBody(**common, center=spec.center_m, half_extents_m=spec.half_extents_m, rotation=rot)


class MovingWorld:
    """The patient's bodies (each with a :class:`Motion`) and the room, at any time."""

    def __init__(
        self,
        bodies: list[tuple[Body, Motion]],
        background: list[Body],
    ) -> None:
        self.bodies = bodies
        self.background = background
        self._static = SimWorld([b for b, _ in bodies], background) if bodies else None
        self.moving = [(b, m) for b, m in bodies if not m.is_static]

    def at(self, t: float) -> SimWorld | None:
        """The :class:`SimWorld` with every body at its pose at ``t`` (meshes re-used)."""
        world = self._static
        if world is None:
            return None
        for body, motion in self.moving:
            world = world.moved(body.name, motion.displacement(t))
        return world

    def closest(self, hip: FloatArray, t: float) -> tuple[float, FloatArray, FloatArray, int]:
        """``(distance, point, normal, body index)`` of the closest body surface to ``hip``."""
        best = (math.inf, np.zeros(3), np.array([0.0, 0.0, 1.0]), -1)
        for i, (body, motion) in enumerate(self.bodies):
            disp = motion.displacement(t)
            sp = body.closest_point(hip - disp, 0.0)
            if sp.distance_m < best[0]:
                best = (sp.distance_m, sp.point + disp, sp.normal, i)
        return best


# ----- cameras -----------------------------------------------------------------------------------
@dataclass
class SimCamera:
    """One declared camera: its schedule, the rendering camera (d435) and its pipeline.

    ``camera`` and ``pipeline`` are ``None`` for an ``oracle`` (the true closest body point within
    ``oracle_reach_m``, with noise). ``frames`` counts the frames that came due (a run advances it).
    """

    spec: CameraSpec
    phase_s: float
    camera: SimDepthCamera | None
    pipeline: CameraPipeline | None
    oracle_reach_m: float
    frames: int = 0

    def next_time(self) -> float:
        return self.phase_s + self.frames / self.spec.rate_hz


def camera_pose(spec: CameraSpec, default_target: FloatArray) -> FloatArray:
    """``pose_world_camera`` of a camera spec (placements as :func:`paper_cameras`)."""
    target = np.array(spec.target_m) if spec.target_m else default_target
    if spec.placement == "custom":
        eye = np.array(spec.position_m)
    else:
        yaw_deg = PLACEMENT_YAW_DEG[spec.placement]
        eye = placement_eye(target, yaw_deg, spec.distance_m, spec.height_m)
    if np.linalg.norm(target - eye) < 1e-6:
        raise ConfigError(f"cameras[{spec.name}]: position_m equals the target")
    return look_at(eye, target)


# ----- the builders ------------------------------------------------------------------------------
def build_robot(scene: Scene) -> RobotModel:
    """The exoskeleton's model (the scene's URDF, or the shipped one)."""
    return RobotModel.load(scene.config.robot.urdf or None)


def initial_joints(scene: Scene, robot: RobotModel) -> FloatArray:
    """The start posture: ``robot.q0_rad``, else IK to ``robot.hip0_m``, else the home posture.

    Raises :class:`InfeasibleSceneError` for a posture outside the joint limits or a HIP out of
    reach, :class:`ConfigError` for the wrong number of joints.
    """
    rs = scene.config.robot
    n = robot.n_joints
    if rs.q0_rad:
        if len(rs.q0_rad) != n:
            raise ConfigError(f"robot.q0_rad: expected {n} joint positions, got {len(rs.q0_rad)}")
        q = np.array(rs.q0_rad)
        if np.any(q < robot.q_min) or np.any(q > robot.q_max):
            raise InfeasibleSceneError("robot.q0_rad: outside the joint limits")
        return q
    if rs.hip0_m:
        q, err = solve_hip_ik(robot, rs.hip0_m)
        if err > rs.ik_tolerance_m:
            raise InfeasibleSceneError(
                f"robot.hip0_m = {list(rs.hip0_m)}: out of the robot's reach "
                f"(closest {err * 1e3:.1f} mm away)"
            )
        return q
    return np.array(robot.q_home)


def build_world(scene: Scene, hip0: FloatArray) -> MovingWorld:
    """The declared bodies with their motions, the moving surface (placed ``start_gap_m`` from
    the HIP sphere at ``hip0``) and the room."""
    bodies: list[tuple[Body, Motion]] = []
    for spec in scene.bodies:
        motion = Motion(np.array(spec.velocity_mps), spec.motion_start_s, spec.motion_duration_s)
        bodies.append((body_from_spec(spec), motion))
    if scene.has_surface:
        bodies.append(_surface_body(scene, hip0))
    background = [body_from_spec(spec) for spec in scene.background]
    return MovingWorld(bodies, background)


def _surface_body(scene: Scene, hip0: FloatArray) -> tuple[Body, Motion]:
    s = scene.config.surface
    direction = np.array(s.direction) / np.linalg.norm(s.direction)
    hz = s.half_extents_m[2]
    center = hip0 - direction * (scene.config.robot.hip_radius_m + s.start_gap_m + hz)
    rot = rotation_between([0.0, 0.0, 1.0], direction)
    body = BoxBody(
        name=s.name, part=s.part, center=center, half_extents_m=s.half_extents_m, rotation=rot
    )
    return body, Motion(direction * s.speed_mps, s.start_s, s.travel_m / s.speed_mps)


def build_walls(scene: Scene) -> tuple[Wall, ...]:
    """The declared walls (``haptic``: rendered by the tick; ``fixed``: the controller's)."""
    return tuple(Wall.make(w.name, w.point_m, w.normal, w.level, w.part) for w in scene.walls)


def build_pipeline(scene: Scene, spec: CameraSpec) -> CameraPipeline | None:
    """The perception pipeline of one camera (its own: it keeps per-camera state), or ``None``
    for an ``oracle``, which hands out estimates without perceiving."""
    if spec.model != "d435":
        return None
    return CameraPipeline(scene.config.perception, camera=spec.name)


def build_cameras(scene: Scene, hip0: FloatArray) -> tuple[SimCamera, ...]:
    """The declared cameras with their schedules: camera ``k`` of ``n`` at rate ``r`` fires at
    ``k / (r n) + m / r`` unless it sets ``phase_s``; a d435 renders the world from its pose
    (aimed at ``hip0`` unless it names a target) and has its pipeline."""
    cameras: list[SimCamera] = []
    n_cams = len(scene.cameras)
    default_reach = scene.config.perception.crop.workspace_radius_m
    for k, spec in enumerate(scene.cameras):
        phase = spec.phase_s if spec.phase_s >= 0.0 else k / (spec.rate_hz * n_cams)
        cam = None
        if spec.model == "d435":
            intr = CameraIntrinsics.d435(spec.width_px, spec.height_px, spec.hfov_deg)
            if spec.width_px // spec.decimation < 8 or spec.height_px // spec.decimation < 8:
                raise ConfigError(f"cameras[{spec.name}].decimation: image too small")
            cam = SimDepthCamera(
                spec.name,
                intr,
                camera_pose(spec, hip0),
                spec.noise,
                decimation=spec.decimation,
            )
        pipe = build_pipeline(scene, spec)
        reach = spec.oracle_range_m or default_reach
        cameras.append(SimCamera(spec, phase, cam, pipe, reach))
    return tuple(cameras)


def build_fusion(scene: Scene, cameras: Sequence[SimCamera]) -> SurfaceFusion | None:
    """The surface fusion, only when a camera feeds it (else the walls alone are the surface)."""
    return SurfaceFusion(scene.config.fusion) if cameras else None


def scene_controller_config(scene: Scene) -> Any:
    """The scene's controller table as the closed loop uses it: fixed walls keep the HIP sphere
    out, like every other surface, unless the scene sets ``controller.walls.margin_m``."""
    controller_cfg = scene.config.controller
    if "margin_m" not in scene.data.get("controller", {}).get("walls", {}):
        controller_cfg = controller_cfg.replace_path(
            "walls.margin_m", scene.config.robot.hip_radius_m
        )
    return controller_cfg


def build_scene_controller(
    scene: Scene, robot: RobotModel, walls: Sequence[Wall]
) -> HierarchicalController:
    """The hierarchical controller of the scene (its ``fixed`` walls at level 3)."""
    return build_controller(robot, scene_controller_config(scene), walls)


def build_loop(
    scene: Scene,
    robot: RobotModel,
    controller: HierarchicalController,
    fusion: SurfaceFusion | None,
    walls: Sequence[Wall],
) -> HapticLoop:
    """The control tick at the scene's rate, with its haptics, HIP radius, fusion and walls."""
    cfg = scene.config
    return HapticLoop(
        robot,
        controller,
        cfg.haptics,
        hip_radius_m=cfg.robot.hip_radius_m,
        dt=1.0 / cfg.loop.rate_hz,
        fusion=fusion,
        walls=walls,
    )


def build_patient(scene: Scene, q0: FloatArray, hip0: FloatArray) -> PatientArm | None:
    """The simulated patient's arm (intent script from the waypoints, muscle and posture
    spring-dampers), or ``None`` without a ``[patient]`` table."""
    if not scene.has_patient:
        return None
    cfg = scene.config.patient
    base = hip0 if cfg.frame == "hip0" else np.zeros(3)
    waypoints: list[Waypoint] = []
    t_prev, p_prev = 0.0, hip0
    for i, wp in enumerate(scene.waypoints):
        p = base + np.array(wp.position_m)
        if i == 0 and wp.t_s < 0.0:
            t = 0.0
        elif wp.t_s >= 0.0:
            t = wp.t_s
        else:
            t = t_prev + segment_time(p_prev, p, wp.speed_mps, wp.profile)
        if waypoints and not t > t_prev:
            raise ConfigError(
                f"patient.waypoints[{i}].t_s = {t}: must be after the previous arrival "
                f"and hold ({t_prev:g} s)"
            )
        waypoints.append(Waypoint(t, p, wp.profile))
        t_prev, p_prev = t, p
        if wp.hold_s > 0.0:
            t_prev = t + wp.hold_s
            waypoints.append(Waypoint(t_prev, p, "linear"))
    if not waypoints:
        waypoints = [Waypoint(0.0, hip0.copy())]
    return PatientArm(
        IntentScript(waypoints, cfg.repeat_s, repeat_name="patient.repeat_s"),
        mass_kg=cfg.mass_kg,
        stiffness_n_per_m=cfg.stiffness_n_per_m,
        damping_n_s_per_m=cfg.damping_n_s_per_m,
        posture=q0,
        posture_stiffness_nm_per_rad=cfg.posture_stiffness_nm_per_rad,
        posture_damping_nms_per_rad=cfg.posture_damping_nms_per_rad,
    )


def seeded_noise(scene: Scene) -> np.random.Generator:
    """The scene's seeded noise stream: oracle estimates and the force sensor draw from it."""
    return np.random.default_rng(scene.config.scene.seed)


def true_margin(
    world: MovingWorld, walls: Sequence[Wall], hip_radius_m: float, hip: FloatArray, t: float
) -> tuple[float, float, float, FloatArray, FloatArray, FloatArray]:
    """``(margin, body margin, wall margin, point, normal, surface velocity)`` at ``t``.

    Margins are true free distances of the HIP sphere (m, negative = penetration); ``inf``
    where the scene has no such surface. Point/normal belong to the closest one.
    """
    r = hip_radius_m
    d_body, point, normal, idx = world.closest(hip, t)
    velocity = world.bodies[idx][1].velocity_at(t) if idx >= 0 else np.zeros(3)
    body_margin = d_body - r
    wall_margin = math.inf
    for wall in walls:
        d = wall.distance(hip) - r
        if d < wall_margin:
            wall_margin = d
            if d < body_margin:
                point, normal, velocity = wall.closest(hip), wall.normal.copy(), np.zeros(3)
    return min(body_margin, wall_margin), body_margin, wall_margin, point, normal, velocity


def check_start(
    world: MovingWorld, walls: Sequence[Wall], hip_radius_m: float, hip0: FloatArray
) -> None:
    """Raise :class:`InfeasibleSceneError` if the HIP sphere starts inside a body or a wall."""
    margin = true_margin(world, walls, hip_radius_m, hip0, 0.0)[0]
    if margin < 0.0:
        raise InfeasibleSceneError(
            f"robot.hip0_m: the HIP sphere starts {-margin * 1e3:.1f} mm inside a surface"
        )


# ----- the assembly ------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Assembly:
    """The parts of one scene, built by :func:`assemble` (see the module docstring)."""

    scene: Scene
    robot: RobotModel
    q0: FloatArray
    hip0: FloatArray
    world: MovingWorld
    walls: tuple[Wall, ...]
    cameras: tuple[SimCamera, ...]
    fusion: SurfaceFusion | None
    controller: HierarchicalController
    loop: HapticLoop
    patient: PatientArm | None

    @property
    def dt(self) -> float:
        """The control period (s)."""
        return 1.0 / self.scene.config.loop.rate_hz

    @property
    def hip_radius_m(self) -> float:
        return self.scene.config.robot.hip_radius_m

    def true_margin(
        self, hip: FloatArray, t: float
    ) -> tuple[float, float, float, FloatArray, FloatArray, FloatArray]:
        """The ground truth at ``hip`` and ``t`` (:func:`true_margin`); never for the controller."""
        return true_margin(self.world, self.walls, self.hip_radius_m, hip, t)

    def oracle_estimate(
        self, cam: SimCamera, t: float, hip: FloatArray, rng: np.random.Generator
    ) -> SurfaceEstimate:
        """What the oracle camera ``cam`` reports at ``t`` for the HIP at ``hip``: the true
        closest body point within its reach, with its noise drawn from ``rng``; beyond the reach,
        an invalid estimate that proves the space free up to it."""
        spec = cam.spec
        d, point, normal, idx = self.world.closest(hip, t)
        reach = cam.oracle_reach_m
        if idx < 0 or d > reach:
            # The oracle knows: nothing within its reach is a proof of free space.
            free = d if idx >= 0 else reach
            return SurfaceEstimate.invalid(
                t, spec.name, "oracle: nothing in range", hip=hip, free_m=min(free, reach)
            )
        c = point + rng.normal(0.0, spec.oracle_centroid_noise_m, 3)
        tilt = rng.normal(0.0, math.radians(spec.oracle_normal_noise_deg), 3)
        n = normal + np.cross(tilt, normal)
        return SurfaceEstimate(t, spec.name, c, n / np.linalg.norm(n), True, quality=1.0)

    def capture(
        self,
        cam: SimCamera,
        t: float,
        q: FloatArray,
        hip: FloatArray,
        rng: np.random.Generator,
        frame_sink: FrameSink | None = None,
    ) -> SurfaceEstimate:
        """The estimate of ``cam`` at ``t`` with the robot at ``q`` (its link capsules occlude
        the view and are cut from the cloud), for the HIP at ``hip``.

        An oracle is :meth:`oracle_estimate` (noise from ``rng``); a d435 renders only the pixels
        its crop reads unless ``frame_sink`` (a recorder) takes the frames: then it gets the whole
        frame, and ``frame_sink(frame, hip, exclude, estimate)`` is called.
        """
        if cam.camera is None:
            return self.oracle_estimate(cam, t, hip, rng)
        world = self.world.at(t)
        assert world is not None and cam.pipeline is not None  # cameras need bodies (loader)
        capsules = self.robot.link_capsules(q)
        roi = None
        if frame_sink is None:
            roi = cam.camera.workspace_roi(hip, cam.pipeline.config.crop)
        frame = cam.camera.render(world, t, occluders=capsules, roi=roi)
        est = cam.pipeline.process_depth(frame, hip, exclude=capsules)
        if frame_sink is not None:
            frame_sink(frame, hip, capsules, est)
        return est


def assemble(scene: Scene) -> Assembly:
    """Build every part ``scene`` declares (see the module docstring).

    Raises
    ------
    InfeasibleSceneError
        If the initial HIP is out of reach or starts inside a body or behind a wall.
    ConfigError
        For declarations that do not fit the robot (wrong number of joints, ...).
    """
    robot = build_robot(scene)
    q0 = initial_joints(scene, robot)
    hip0 = robot.hip_position_at(q0)
    world = build_world(scene, hip0)
    walls = build_walls(scene)
    cameras = build_cameras(scene, hip0)
    fusion = build_fusion(scene, cameras)
    controller = build_scene_controller(scene, robot, walls)
    loop = build_loop(scene, robot, controller, fusion, walls)
    patient = build_patient(scene, q0, hip0)
    check_start(world, walls, scene.config.robot.hip_radius_m, hip0)
    return Assembly(
        scene, robot, q0, hip0, world, walls, cameras, fusion, controller, loop, patient
    )


__all__ = [
    "Assembly",
    "FrameSink",
    "InfeasibleSceneError",
    "Motion",
    "MovingWorld",
    "SimCamera",
    "assemble",
    "body_from_spec",
    "build_cameras",
    "build_fusion",
    "build_loop",
    "build_patient",
    "build_pipeline",
    "build_robot",
    "build_scene_controller",
    "build_walls",
    "build_world",
    "camera_pose",
    "check_start",
    "initial_joints",
    "scene_controller_config",
    "seeded_noise",
    "true_margin",
]
