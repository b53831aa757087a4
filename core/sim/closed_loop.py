"""The closed-loop simulation of a scene: cameras, perception, fusion, the tick, the exoskeleton.

Everything runs in simulated time and is deterministic given the scene (seeded noise). Per
control period ``dt`` (800 Hz by default):

1. camera frames due by now are captured: each simulated camera renders the world (the patient's
   bodies, moved to their pose at this time, and the room) with the robot's link capsules as
   occluders, its :class:`~hapticloud.core.perception.CameraPipeline` turns the frame into an
   estimate for the current HIP, and the estimate is queued until ``t + latency_s``
   (transfer and processing); camera ``k`` of ``n`` at rate ``r`` fires at ``k / (r n) + m / r``;
2. queued estimates whose time has come go to ``fusion.add`` and the fusion is refitted
   (``prepare``: outside the tick, as the camera thread does on the robot);
3. the tick (:class:`~hapticloud.core.loop.HapticLoop`) computes the torques from the measured
   joint state and the force sensor's last reading;
4. the plant (:class:`~.exo.ExoPlant`) advances ``dt`` with those torques and the patient's force.

Only what the scene declares is built: no cameras -> no pipeline, no fusion (the haptic surface
comes from the walls alone); one camera -> its estimates alone feed the fusion; no ``[patient]``
-> nobody pushes the handle. Ground truth (the true distance of the HIP sphere from every body
and wall) is recorded every tick; it never reaches the controller.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..camera import CameraIntrinsics, DepthFrame, look_at
from ..control import ControlStatus
from ..errors import ConfigError
from ..fusion import SurfaceFusion
from ..geometry import Capsule, rotation_between
from ..limits import MAX_DURATION_S
from ..loop import HapticLoop, Wall, admit, build_controller, is_fallback
from ..perception import CameraPipeline, SurfaceEstimate
from ..robot import RobotModel
from ..scene import BodySpec, CameraSpec, Scene
from .bodies import Body, BoxBody, CapsuleBody, CylinderBody, EllipsoidBody, SphereBody
from .depth_camera import SimDepthCamera
from .exo import ExoPlant, solve_hip_ik
from .patient import IntentScript, PatientArm, Waypoint, segment_time
from .scenes import rotation_xyz
from .world import SimWorld

FloatArray = NDArray[np.float64]

STATUS_CODES = {s: i for i, s in enumerate(ControlStatus)}


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
    """One declared camera: its schedule, the rendering camera (d435) and its pipeline."""

    spec: CameraSpec
    phase_s: float
    camera: SimDepthCamera | None
    pipeline: CameraPipeline | None
    frames: int = 0

    def next_time(self) -> float:
        return self.phase_s + self.frames / self.spec.rate_hz


def camera_pose(spec: CameraSpec, default_target: FloatArray) -> FloatArray:
    """``pose_world_camera`` of a camera spec (placements as :func:`paper_cameras`)."""
    target = np.array(spec.target_m) if spec.target_m else default_target
    if spec.placement == "custom":
        eye = np.array(spec.position_m)
    else:
        yaw = 0.0 if spec.placement == "front" else math.radians(-45.0)
        eye = target + spec.distance_m * np.array([math.cos(yaw), math.sin(yaw), 0.0])
        eye = eye + np.array([0.0, 0.0, spec.height_m])
    if np.linalg.norm(target - eye) < 1e-6:
        raise ConfigError(f"cameras[{spec.name}]: position_m equals the target")
    return look_at(eye, target)


# ----- records -----------------------------------------------------------------------------------
@dataclass
class FrameRecord:
    """One camera estimate with the truth at its HIP (for the report and Fig. 8)."""

    t: float
    camera: str
    valid: bool
    centroid: FloatArray
    normal: FloatArray
    hip: FloatArray
    true_point: FloatArray
    true_normal: FloatArray
    true_distance_m: float
    perception_ms: float
    reason: str = ""
    quality: float = 0.0
    admitted: bool = True
    fallback: bool = False


@dataclass
class RunRecord:
    """Everything a run produced: per-tick arrays, per-frame estimates, timings, build info."""

    scene: Scene
    dt: float
    hip_radius_m: float
    arrays: dict[str, FloatArray]
    frames: list[FrameRecord]
    wall_time_s: float
    timing_s: dict[str, float]
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_ticks(self) -> int:
        return int(self.arrays["t"].shape[0])


_VEC_FIELDS = (
    "hip",
    "hip_velocity",
    "intent",
    "muscle_force",
    "hand_force",
    "true_point",
    "true_normal",
    "true_velocity",
    "fused_centroid",
    "fused_normal",
    "target_centroid",
    "target_normal",
    "fused_velocity",
)
_SCALAR_FIELDS = (
    "t",
    "margin",
    "body_margin",
    "wall_margin",
    "d_proj",
    "approach",
    "nearest",
    "rows",
    "binding",
    "violation",
    "fused_valid",
    "solve_us",
    "step_us",
    "tick_us",
    "clamped",
    "status",
    "fused_age",
    "space",
)


# ----- the simulation ----------------------------------------------------------------------------
def scene_controller_config(scene: Scene) -> Any:
    """The scene's controller table as the closed loop uses it: fixed walls keep the HIP sphere
    out, like every other surface, unless the scene sets ``controller.walls.margin_m``."""
    controller_cfg = scene.config.controller
    if "margin_m" not in scene.data.get("controller", {}).get("walls", {}):
        controller_cfg = controller_cfg.replace_path(
            "walls.margin_m", scene.config.robot.hip_radius_m
        )
    return controller_cfg


class ClosedLoopSim:
    """A scene built for a closed-loop run (see the module docstring).

    Parameters
    ----------
    scene
        The validated scene (:func:`~hapticloud.core.scene.load_scene`).

    Raises
    ------
    InfeasibleSceneError
        If the initial HIP is out of reach or starts inside a body or behind a wall.
    ConfigError
        For declarations that do not fit the robot (wrong number of joints, ...).
    """

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        cfg = scene.config
        self.dt = 1.0 / cfg.loop.rate_hz
        self.hip_radius_m = cfg.robot.hip_radius_m
        self.rng = np.random.default_rng(cfg.scene.seed)
        # Its own stream: losing frames must not change the noise of the frames that arrive.
        self._drops = np.random.default_rng([cfg.scene.seed, 1])
        urdf = cfg.robot.urdf or None
        self.robot = RobotModel.load(urdf)
        plant_model = RobotModel.load(urdf)
        self.q0 = self._initial_q(self.robot)
        self.hip0 = self.robot.hip_position_at(self.q0)

        # The world: declared bodies, the moving surface, the room.
        bodies: list[tuple[Body, Motion]] = []
        for spec in scene.bodies:
            motion = Motion(
                np.array(spec.velocity_mps), spec.motion_start_s, spec.motion_duration_s
            )
            bodies.append((body_from_spec(spec), motion))
        if scene.has_surface:
            bodies.append(self._surface_body())
        background = [body_from_spec(spec) for spec in scene.background]
        self.world = MovingWorld(bodies, background)
        self.walls = [Wall.make(w.name, w.point_m, w.normal, w.level, w.part) for w in scene.walls]

        # Perception: only the declared cameras; fusion only with a camera.
        self.cameras: list[SimCamera] = []
        n_cams = len(scene.cameras)
        for k, spec in enumerate(scene.cameras):
            phase = spec.phase_s if spec.phase_s >= 0.0 else k / (spec.rate_hz * n_cams)
            if spec.model == "d435":
                intr = CameraIntrinsics.d435(spec.width_px, spec.height_px, spec.hfov_deg)
                if spec.width_px // spec.decimation < 8 or spec.height_px // spec.decimation < 8:
                    raise ConfigError(f"cameras[{spec.name}].decimation: image too small")
                cam = SimDepthCamera(
                    spec.name,
                    intr,
                    camera_pose(spec, self.hip0),
                    spec.noise,
                    decimation=spec.decimation,
                )
                pipe = CameraPipeline(cfg.perception, camera=spec.name)
            else:
                cam, pipe = None, None
            self.cameras.append(SimCamera(spec, phase, cam, pipe))
        self.fusion = SurfaceFusion(cfg.fusion) if self.cameras else None
        #: Called with ``(frame, hip, exclude, estimate)`` after each rendered camera frame is
        #: processed (a recorder's hook; it must not change what the run computes).
        self.frame_sink: (
            Callable[[DepthFrame, FloatArray, list[Capsule], SurfaceEstimate], None] | None
        ) = None

        # Control: the controller (fixed walls at level 3) and the tick.
        controller_cfg = scene_controller_config(scene)
        self.controller = build_controller(self.robot, controller_cfg, self.walls)
        self.loop = HapticLoop(
            self.robot,
            self.controller,
            cfg.haptics,
            hip_radius_m=self.hip_radius_m,
            dt=self.dt,
            fusion=self.fusion,
            walls=self.walls,
        )

        # The patient and the plant.
        self.patient = self._patient() if scene.has_patient else None
        self.plant = ExoPlant(
            plant_model,
            self.q0,
            dt=self.dt,
            substeps=cfg.loop.substeps,
            hand_mass_kg=cfg.patient.mass_kg if self.patient else 0.0,
            joint_friction_nms_per_rad=cfg.robot.joint_friction_nms_per_rad,
        )
        margin = self.true_margin(self.hip0, 0.0)[0]
        if margin < 0.0:
            raise InfeasibleSceneError(
                f"robot.hip0_m: the HIP sphere starts {-margin * 1e3:.1f} mm inside a surface"
            )

    # ----- build helpers --------------------------------------------------------------------------
    def _initial_q(self, model: RobotModel) -> FloatArray:
        rs = self.scene.config.robot
        n = model.n_joints
        if rs.q0_rad:
            if len(rs.q0_rad) != n:
                raise ConfigError(
                    f"robot.q0_rad: expected {n} joint positions, got {len(rs.q0_rad)}"
                )
            q = np.array(rs.q0_rad)
            if np.any(q < model.q_min) or np.any(q > model.q_max):
                raise InfeasibleSceneError("robot.q0_rad: outside the joint limits")
            return q
        if rs.hip0_m:
            q, err = solve_hip_ik(model, rs.hip0_m)
            if err > rs.ik_tolerance_m:
                raise InfeasibleSceneError(
                    f"robot.hip0_m = {list(rs.hip0_m)}: out of the robot's reach "
                    f"(closest {err * 1e3:.1f} mm away)"
                )
            return q
        return np.array(model.q_home)

    def _surface_body(self) -> tuple[Body, Motion]:
        s = self.scene.config.surface
        direction = np.array(s.direction) / np.linalg.norm(s.direction)
        hz = s.half_extents_m[2]
        center = self.hip0 - direction * (self.hip_radius_m + s.start_gap_m + hz)
        rot = rotation_between([0.0, 0.0, 1.0], direction)
        body = BoxBody(
            name=s.name, part=s.part, center=center, half_extents_m=s.half_extents_m, rotation=rot
        )
        return body, Motion(direction * s.speed_mps, s.start_s, s.travel_m / s.speed_mps)

    def _patient(self) -> PatientArm:
        cfg = self.scene.config.patient
        base = self.hip0 if cfg.frame == "hip0" else np.zeros(3)
        waypoints: list[Waypoint] = []
        t_prev, p_prev = 0.0, self.hip0
        for i, wp in enumerate(self.scene.waypoints):
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
            waypoints = [Waypoint(0.0, self.hip0.copy())]
        return PatientArm(
            IntentScript(waypoints),
            mass_kg=cfg.mass_kg,
            stiffness_n_per_m=cfg.stiffness_n_per_m,
            damping_n_s_per_m=cfg.damping_n_s_per_m,
            posture=self.q0,
            posture_stiffness_nm_per_rad=cfg.posture_stiffness_nm_per_rad,
            posture_damping_nms_per_rad=cfg.posture_damping_nms_per_rad,
        )

    # ----- ground truth ---------------------------------------------------------------------------
    def true_margin(
        self, hip: FloatArray, t: float
    ) -> tuple[float, float, float, FloatArray, FloatArray, FloatArray]:
        """``(margin, body margin, wall margin, point, normal, surface velocity)`` at ``t``.

        Margins are true free distances of the HIP sphere (m, negative = penetration); ``inf``
        where the scene has no such surface. Point/normal belong to the closest one.
        """
        r = self.hip_radius_m
        d_body, point, normal, idx = self.world.closest(hip, t)
        velocity = self.world.bodies[idx][1].velocity_at(t) if idx >= 0 else np.zeros(3)
        body_margin = d_body - r
        wall_margin = math.inf
        for wall in self.walls:
            d = wall.distance(hip) - r
            if d < wall_margin:
                wall_margin = d
                if d < body_margin:
                    point, normal, velocity = wall.closest(hip), wall.normal.copy(), np.zeros(3)
        return min(body_margin, wall_margin), body_margin, wall_margin, point, normal, velocity

    # ----- cameras --------------------------------------------------------------------------------
    def _capture(self, cam: SimCamera, t: float, q: FloatArray, hip: FloatArray) -> SurfaceEstimate:
        spec = cam.spec
        if cam.camera is None:  # oracle: the true closest body point, with noise
            d, point, normal, idx = self.world.closest(hip, t)
            reach = spec.oracle_range_m or self.scene.config.perception.crop.workspace_radius_m
            if idx < 0 or d > reach:
                # The oracle knows: nothing within its reach is a proof of free space.
                free = d if idx >= 0 else reach
                return SurfaceEstimate.invalid(
                    t, spec.name, "oracle: nothing in range", hip=hip, free_m=min(free, reach)
                )
            c = point + self.rng.normal(0.0, spec.oracle_centroid_noise_m, 3)
            tilt = self.rng.normal(0.0, math.radians(spec.oracle_normal_noise_deg), 3)
            n = normal + np.cross(tilt, normal)
            return SurfaceEstimate(t, spec.name, c, n / np.linalg.norm(n), True, quality=1.0)
        world = self.world.at(t)
        assert world is not None and cam.pipeline is not None  # cameras need bodies (loader)
        capsules = self.robot.link_capsules(q)
        # Only the pixels the crop reads are ray-cast (the same frame there, 0 elsewhere); a
        # recorder (frame_sink) may store more of the image than that: it gets the whole frame.
        roi = None
        if self.frame_sink is None:
            roi = cam.camera.workspace_roi(hip, cam.pipeline.config.crop)
        frame = cam.camera.render(world, t, occluders=capsules, roi=roi)
        est = cam.pipeline.process_depth(frame, hip, exclude=capsules)
        if self.frame_sink is not None:  # a recorder: what the pipeline saw and what it said
            self.frame_sink(frame, hip, capsules, est)
        return est

    def _lost(self, spec: CameraSpec, t: float) -> bool:
        """A frame that never arrives: the camera stopped, or the link dropped it (seeded)."""
        if 0.0 <= spec.stop_s <= t:
            return True
        return spec.drop_fraction > 0.0 and self._drops.random() < spec.drop_fraction

    # ----- the run --------------------------------------------------------------------------------
    def run(
        self,
        duration_s: float | None = None,
        progress: Callable[[float], None] | None = None,
    ) -> RunRecord:
        """Run ``duration_s`` (default: the scene's) of simulated time; returns the record."""
        cfg = self.scene.config
        duration = cfg.scene.duration_s if duration_s is None else float(duration_s)
        if not duration > 0.0 or not math.isfinite(duration):
            raise ConfigError(f"duration = {duration}: must be a positive number of seconds")
        if duration > MAX_DURATION_S:
            raise ConfigError(f"duration = {duration:g}: must be at most {MAX_DURATION_S:g} s")
        n_ticks = round(duration / self.dt)
        arrays: dict[str, FloatArray] = {k: np.zeros((n_ticks, 3)) for k in _VEC_FIELDS}
        arrays.update({k: np.zeros(n_ticks) for k in _SCALAR_FIELDS})
        arrays["q"] = np.zeros((n_ticks, self.robot.n_joints))
        arrays["tau"] = np.zeros((n_ticks, self.robot.n_joints))
        frames: list[FrameRecord] = []
        pending: deque[tuple[float, SurfaceEstimate]] = deque()
        timing = {"perception": 0.0, "tick": 0.0, "plant": 0.0, "truth": 0.0}
        force_sensor = cfg.robot.force_sensor
        noise_n = cfg.robot.force_sensor_noise_n
        patient = self.patient
        n_joints = self.robot.n_joints

        state = self.plant.state()
        wall_start = time.perf_counter()
        for k in range(n_ticks):
            t = k * self.dt
            # 1. camera frames due now (rendered at the current state), queued for their latency.
            t0 = time.perf_counter()
            for cam in self.cameras:
                while cam.next_time() <= t + 1e-12:
                    cam.frames += 1
                    if self._lost(cam.spec, t):
                        continue
                    est = self._capture(cam, t, state.q, state.hip)
                    admitted = admit(est, cam.spec.min_quality, cam.spec.fuse_fallbacks)
                    if admitted:
                        pending.append((t + cam.spec.latency_s, est))
                    truth = self.world.closest(state.hip, t)
                    frames.append(
                        FrameRecord(
                            t,
                            cam.spec.name,
                            est.valid,
                            est.centroid.copy(),
                            est.normal.copy(),
                            state.hip.copy(),
                            truth[1],
                            truth[2],
                            truth[0],
                            float(est.stage_ms.get("total", 0.0)) if est.stage_ms else 0.0,
                            est.reason,
                            float(est.quality),
                            admitted,
                            is_fallback(est),
                        )
                    )
            # 2. estimates whose latency has passed reach the fusion (refit outside the tick).
            if self.fusion is not None and pending:
                pending = deque(sorted(pending, key=lambda item: item[0]))
                arrived = False
                while pending and pending[0][0] <= t + 1e-12:
                    self.fusion.add(pending.popleft()[1])
                    arrived = True
                if arrived:
                    self.fusion.prepare()
            t1 = time.perf_counter()
            timing["perception"] += t1 - t0

            # 3. the tick, from the measured state and the sensor's last reading.
            tau_int = None
            if force_sensor and patient is not None:
                f_meas = state.hand_force + (
                    self.rng.normal(0.0, noise_n, 3) if noise_n > 0 else 0.0
                )
                tau_int = self.plant.model.hip_jacobian().T @ f_meas
            res = self.loop.tick(t, state.q, state.qd, interaction_torque=tau_int)
            t2 = time.perf_counter()
            timing["tick"] += t2 - t1

            # record (state at t, command computed at t)
            margin, body_m, wall_m, point, normal, s_vel = self.true_margin(state.hip, t)
            t3 = time.perf_counter()
            timing["truth"] += t3 - t2
            fused = self.loop.last_fused
            a = arrays
            a["t"][k] = t
            a["hip"][k] = state.hip
            a["hip_velocity"][k] = state.hip_velocity
            a["q"][k] = state.q
            a["tau"][k] = res.tau
            a["muscle_force"][k] = state.muscle_force
            a["hand_force"][k] = state.hand_force
            a["intent"][k] = patient.intent.position(t) if patient is not None else state.hip
            a["margin"][k] = margin
            a["body_margin"][k] = body_m
            a["wall_margin"][k] = wall_m
            a["true_point"][k] = point
            a["true_normal"][k] = normal
            a["true_velocity"][k] = s_vel
            a["d_proj"][k] = res.d_proj_m
            a["approach"][k] = res.approach_mps
            a["nearest"][k] = res.nearest
            a["rows"][k] = res.rows
            a["binding"][k] = self.loop.last_binding()
            a["violation"][k] = res.violation
            a["fused_valid"][k] = res.fused_valid
            a["solve_us"][k] = res.solve_us
            a["step_us"][k] = res.step_us
            a["tick_us"][k] = res.tick_us
            a["clamped"][k] = res.clamped
            a["status"][k] = STATUS_CODES[res.status]
            a["space"][k] = res.space
            if fused is not None:
                a["fused_centroid"][k] = fused.centroid
                a["fused_normal"][k] = fused.normal
                a["target_centroid"][k] = fused.target_centroid
                a["target_normal"][k] = fused.target_normal
                a["fused_velocity"][k] = fused.velocity
                a["fused_age"][k] = fused.age_s if math.isfinite(fused.age_s) else -1.0
            else:
                a["fused_age"][k] = -1.0

            # 4. the plant advances one period with the torques held.
            state = self.plant.step(res.tau, patient.forces if patient is not None else None)
            timing["plant"] += time.perf_counter() - t3
            if progress is not None and k % 800 == 0:
                progress(t)
        wall_time = time.perf_counter() - wall_start
        info = {
            "q0_rad": self.q0.tolist(),
            "hip0_m": self.hip0.tolist(),
            "cameras": [c.spec.name for c in self.cameras],
            "camera_models": [c.spec.model for c in self.cameras],
            "perception": any(c.camera is not None for c in self.cameras),
            "fusion": self.fusion is not None,
            "merging": len(self.cameras) > 1,
            "bodies": [b.name for b, _ in self.world.bodies],
            "walls": [{"name": w.name, "level": w.level} for w in self.walls],
            "patient": patient is not None,
            "force_sensor": bool(force_sensor and patient is not None),
            "n_joints": n_joints,
            "space_transitions": self.loop.guard.transitions if self.fusion is not None else (),
        }
        if patient is not None:
            info["intent_end_s"] = patient.intent.end_s
        return RunRecord(
            scene=self.scene,
            dt=self.dt,
            hip_radius_m=self.hip_radius_m,
            arrays=arrays,
            frames=frames,
            wall_time_s=wall_time,
            timing_s=timing,
            info=info,
        )


__all__ = [
    "ClosedLoopSim",
    "FrameRecord",
    "InfeasibleSceneError",
    "Motion",
    "MovingWorld",
    "RunRecord",
    "SimCamera",
    "body_from_spec",
    "camera_pose",
]
