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

from ..control import ControlStatus, HierarchicalController
from ..errors import ConfigError
from ..fusion import SurfaceFusion
from ..limits import MAX_DURATION_S
from ..loop import HapticLoop, Wall, admit, is_fallback
from ..perception import SurfaceEstimate
from ..robot import RobotModel
from ..scene import CameraSpec, Scene
from ..scene.assembly import (
    Assembly,
    FrameSink,
    InfeasibleSceneError,
    Motion,
    MovingWorld,
    SimCamera,
    assemble,
    body_from_spec,
    camera_pose,
    scene_controller_config,
    seeded_noise,
)
from .exo import ExoPlant
from .patient import PatientArm

FloatArray = NDArray[np.float64]

STATUS_CODES = {s: i for i, s in enumerate(ControlStatus)}


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


# ----- the plant ---------------------------------------------------------------------------------
def build_plant(
    scene: Scene,
    model: RobotModel,
    q0: FloatArray,
    *,
    held: bool,
    substeps: int | None = None,
    frozen_dynamics: bool = False,
) -> ExoPlant:
    """The exoskeleton's plant as the scene declares it: the control period, ``loop.substeps``
    (unless ``substeps``), the hand's mass at the HIP when a patient holds the handle (``held``)
    and the unmodelled joint friction (``frozen_dynamics``: see :class:`ExoPlant`)."""
    cfg = scene.config
    return ExoPlant(
        model,
        q0,
        dt=1.0 / cfg.loop.rate_hz,
        substeps=cfg.loop.substeps if substeps is None else substeps,
        hand_mass_kg=cfg.patient.mass_kg if held else 0.0,
        joint_friction_nms_per_rad=cfg.robot.joint_friction_nms_per_rad,
        frozen_dynamics=frozen_dynamics,
    )


# ----- the simulation ----------------------------------------------------------------------------
class ClosedLoopSim:
    """A scene built for a closed-loop run (see the module docstring).

    The parts (robot, world, cameras, fusion, controller, tick, patient) are the scene's
    :class:`~hapticloud.core.scene.assembly.Assembly`; the simulation adds the exoskeleton's plant,
    the seeded noise of the run and the run itself.

    Parameters
    ----------
    scene
        The validated scene (:func:`~hapticloud.core.scene.load_scene`), assembled here, or its
        :func:`~hapticloud.core.scene.assembly.assemble` result (the parts keep state: one
        assembly per simulation).

    Raises
    ------
    InfeasibleSceneError
        If the initial HIP is out of reach or starts inside a body or behind a wall.
    ConfigError
        For declarations that do not fit the robot (wrong number of joints, ...).
    """

    def __init__(self, scene: Scene | Assembly) -> None:
        parts = scene if isinstance(scene, Assembly) else assemble(scene)
        self.parts = parts
        self.scene = parts.scene
        cfg = self.scene.config
        self.dt = parts.dt
        self.hip_radius_m = parts.hip_radius_m
        self.rng = seeded_noise(self.scene)
        # Its own stream: losing frames must not change the noise of the frames that arrive.
        self._drops = np.random.default_rng([cfg.scene.seed, 1])
        #: Called with ``(frame, hip, exclude, estimate)`` after each rendered camera frame is
        #: processed (a recorder's hook; it must not change what the run computes).
        self.frame_sink: FrameSink | None = None
        # The exoskeleton itself: its own model, apart from the one the tick computes with.
        model = RobotModel.load(cfg.robot.urdf or None)
        self.plant = build_plant(self.scene, model, parts.q0, held=parts.patient is not None)

    # ----- the assembly's parts (read-only) -------------------------------------------------------
    @property
    def robot(self) -> RobotModel:
        return self.parts.robot

    @property
    def q0(self) -> FloatArray:
        return self.parts.q0

    @property
    def hip0(self) -> FloatArray:
        return self.parts.hip0

    @property
    def world(self) -> MovingWorld:
        return self.parts.world

    @property
    def walls(self) -> tuple[Wall, ...]:
        return self.parts.walls

    @property
    def cameras(self) -> list[SimCamera]:
        return list(self.parts.cameras)

    @property
    def fusion(self) -> SurfaceFusion | None:
        return self.parts.fusion

    @property
    def controller(self) -> HierarchicalController:
        return self.parts.controller

    @property
    def loop(self) -> HapticLoop:
        return self.parts.loop

    @property
    def patient(self) -> PatientArm | None:
        return self.parts.patient

    def true_margin(
        self, hip: FloatArray, t: float
    ) -> tuple[float, float, float, FloatArray, FloatArray, FloatArray]:
        """The ground truth (:meth:`~hapticloud.core.scene.assembly.Assembly.true_margin`)."""
        return self.parts.true_margin(hip, t)

    # ----- cameras --------------------------------------------------------------------------------
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
        parts = self.parts
        patient, cameras, world = parts.patient, parts.cameras, parts.world
        fusion, loop = parts.fusion, parts.loop
        n_joints = self.robot.n_joints

        state = self.plant.state()
        wall_start = time.perf_counter()
        for k in range(n_ticks):
            t = k * self.dt
            # 1. camera frames due now (rendered at the current state), queued for their latency.
            t0 = time.perf_counter()
            for cam in cameras:
                while cam.next_time() <= t + 1e-12:
                    cam.frames += 1
                    if self._lost(cam.spec, t):
                        continue
                    est = self.parts.capture(cam, t, state.q, state.hip, self.rng, self.frame_sink)
                    admitted = admit(est, cam.spec.min_quality, cam.spec.fuse_fallbacks)
                    if admitted:
                        pending.append((t + cam.spec.latency_s, est))
                    truth = world.closest(state.hip, t)
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
            if fusion is not None and pending:
                pending = deque(sorted(pending, key=lambda item: item[0]))
                arrived = False
                while pending and pending[0][0] <= t + 1e-12:
                    fusion.add(pending.popleft()[1])
                    arrived = True
                if arrived:
                    fusion.prepare()
            t1 = time.perf_counter()
            timing["perception"] += t1 - t0

            # 3. the tick, from the measured state and the sensor's last reading.
            tau_int = None
            if force_sensor and patient is not None:
                f_meas = state.hand_force + (
                    self.rng.normal(0.0, noise_n, 3) if noise_n > 0 else 0.0
                )
                tau_int = self.plant.model.hip_jacobian().T @ f_meas
            res = loop.tick(t, state.q, state.qd, interaction_torque=tau_int)
            t2 = time.perf_counter()
            timing["tick"] += t2 - t1

            # record (state at t, command computed at t)
            margin, body_m, wall_m, point, normal, s_vel = parts.true_margin(state.hip, t)
            t3 = time.perf_counter()
            timing["truth"] += t3 - t2
            fused = loop.last_fused
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
            a["binding"][k] = loop.last_binding()
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


# The parts moved to hapticloud.core.scene.assembly; their names stay importable from here.
__all__ = [
    "ClosedLoopSim",
    "FrameRecord",
    "InfeasibleSceneError",
    "Motion",
    "MovingWorld",
    "RunRecord",
    "SimCamera",
    "body_from_spec",
    "build_plant",
    "camera_pose",
    "scene_controller_config",
]
