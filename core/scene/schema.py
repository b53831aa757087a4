"""The scene file's tables: one frozen config class per table, validated like every stage config.

A scene file (TOML) has these tables (``docs/closed-loop.md`` lists every key with its range):

- ``[scene]`` name, description, duration, seed;
- ``[robot]`` the simulated exoskeleton: URDF, initial joints or initial HIP, HIP radius, handle
  force sensor, joint friction;
- ``[loop]`` control rate and integration substeps;
- ``[[cameras]]`` zero, one or more simulated cameras (placement, resolution, rate, latency,
  noise); no cameras means no perception at all;
- ``[[bodies]]`` the patient's surfaces (sphere, ellipsoid, capsule, cylinder, box; ISO body part;
  optional constant-velocity motion), ``[[background]]`` the room (seen, never touched);
- ``[surface]`` optional: a flat plate moving at constant speed (the paper's Fig. 12);
- ``[[walls]]`` virtual planes (point + normal), rendered haptically or as fixed walls;
- ``[patient]`` + ``[[patient.waypoints]]`` the arm's impedance and its intent script;
- ``[perception]``, ``[fusion]``, ``[haptics]``, ``[controller]`` parameter overrides of the
  pipeline's own tables.

List entries (cameras, bodies, walls, waypoints) are each one of the classes below; the fixed
tables are nested in :class:`SceneConfig`. Cross-field rules are in each class's ``check``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from ..config import StageConfig, nested, param
from ..control import ControllerConfig
from ..errors import ConfigError
from ..fusion import FusionConfig
from ..haptics import body_region
from ..limits import MAX_DURATION_S
from ..loop import HapticsConfig
from ..perception import PerceptionConfig
from ..sim.bodies import BODY_PARTS
from ..sim.noise import DepthNoiseConfig
from ..sim.patient import PROFILES
from ..sim.scenes import PLACEMENT_YAW_DEG

BODY_TYPES = ("sphere", "ellipsoid", "capsule", "cylinder", "box")
PLACEMENTS = (*PLACEMENT_YAW_DEG, "custom")
CAMERA_MODELS = ("d435", "oracle")

#: Keys each body type needs (besides name, type, part).
BODY_KEYS: dict[str, tuple[str, ...]] = {
    "sphere": ("center_m", "radius_m"),
    "ellipsoid": ("center_m", "semi_axes_m"),
    "capsule": ("a_m", "b_m", "radius_m"),
    "cylinder": ("a_m", "b_m", "radius_m"),
    "box": ("center_m", "half_extents_m"),
}


def _need3(value: tuple[float, ...], name: str, *, optional: bool = False) -> None:
    if optional and not value:
        return
    if len(value) != 3:
        raise ConfigError(f"{name} = {list(value)}: expected 3 numbers")


def _nonzero(value: tuple[float, ...], name: str) -> None:
    if math.sqrt(sum(v * v for v in value)) < 1e-9:
        raise ConfigError(f"{name} = {list(value)}: must be a non-zero direction")


@dataclass(frozen=True)
class SceneMeta(StageConfig):
    """``[scene]``: what the scene is and how long it runs."""

    name: str = param("scene", doc="short name (reports, figure titles)")
    description: str = param("", doc="one line saying what the scene shows")
    duration_s: float = param(
        5.0, lo=0.0, hi=MAX_DURATION_S, lo_open=True, unit="s", doc="run length"
    )
    seed: int = param(0, lo=0, hi=2**31 - 1, doc="seed of every random source of the run")


@dataclass(frozen=True)
class RobotSpec(StageConfig):
    """``[robot]``: the simulated exoskeleton and its HIP."""

    urdf: str = param("", doc="URDF path ('' = the shipped ANYexo-like model)")
    q0_rad: tuple[float, ...] = param(
        (), lo=-10.0, hi=10.0, unit="rad", doc="initial joints (empty: IK to hip0_m, or home)"
    )
    hip0_m: tuple[float, ...] = param(
        (), lo=-5.0, hi=5.0, unit="m", doc="initial HIP position, reached by IK from home"
    )
    hip_radius_m: float = param(0.04, lo=0.0, hi=0.2, unit="m", doc="HIP sphere radius")
    force_sensor: bool = param(
        True, doc="the handle's force sensor enters the controller's equation of motion"
    )
    force_sensor_noise_n: float = param(
        0.2, lo=0.0, hi=20.0, unit="N", doc="white noise std of each force-sensor axis"
    )
    joint_friction_nms_per_rad: float = param(
        0.2, lo=0.0, hi=20.0, unit="N m s/rad", doc="viscous joint friction (unmodelled)"
    )
    ik_tolerance_m: float = param(
        0.002, lo=1e-5, hi=0.05, unit="m", doc="hip0_m farther than this from reach: infeasible"
    )

    def check(self) -> None:
        _need3(self.hip0_m, "hip0_m", optional=True)
        if self.q0_rad and self.hip0_m:
            raise ConfigError("q0_rad, hip0_m: give one of them, not both")


@dataclass(frozen=True)
class LoopSpec(StageConfig):
    """``[loop]``: control rate and plant integration."""

    rate_hz: float = param(800.0, lo=100.0, hi=4000.0, unit="Hz", doc="control tick rate")
    substeps: int = param(4, lo=1, hi=50, doc="plant integration steps per control tick")


@dataclass(frozen=True)
class CameraSpec(StageConfig):
    """One ``[[cameras]]`` entry: a simulated depth camera and its pipeline."""

    name: str = param("camera", doc="camera name (unique)")
    model: str = param(
        "d435",
        choices=CAMERA_MODELS,
        doc="d435: rendered depth + perception; oracle: true closest point + noise (fast)",
    )
    placement: str = param(
        "front",
        choices=PLACEMENTS,
        doc="front / right45 (the paper's), left45 (its mirror) or custom (position_m)",
    )
    target_m: tuple[float, ...] = param(
        (), lo=-5.0, hi=5.0, unit="m", doc="point the camera looks at (empty: the initial HIP)"
    )
    distance_m: float = param(
        0.75, lo=0.2, hi=5.0, unit="m", doc="horizontal distance from the target (placements)"
    )
    height_m: float = param(0.2, lo=-2.0, hi=3.0, unit="m", doc="height above the target")
    position_m: tuple[float, ...] = param(
        (), lo=-10.0, hi=10.0, unit="m", doc="custom: the optical centre"
    )
    rate_hz: float = param(30.0, lo=1.0, hi=120.0, unit="Hz", doc="frame rate")
    phase_s: float = param(
        -1.0, lo=-1.0, hi=1.0, unit="s", doc="first frame time (-1: interleave k/(rate n))"
    )
    latency_s: float = param(
        0.015,
        lo=0.0,
        hi=2.0,
        unit="s",
        doc="exposure to estimate available (transfer + perception)",
    )
    drop_fraction: float = param(
        0.0, lo=0.0, hi=0.99, doc="share of frames lost on the way (seeded; a degraded link)"
    )
    stop_s: float = param(
        -1.0,
        lo=-1.0,
        hi=3600.0,
        unit="s",
        doc="the camera sends nothing from this time on (-1: never)",
    )
    min_quality: float = param(
        0.5, lo=0.0, hi=1.0, doc="estimates below this quality are not fused"
    )
    fuse_fallbacks: bool = param(
        False, doc="also fuse the estimates for which the estimator fell back to the shells"
    )
    width_px: int = param(848, lo=16, hi=4096, doc="full-resolution width")
    height_px: int = param(480, lo=16, hi=4096, doc="full-resolution height")
    hfov_deg: float = param(87.0, lo=10.0, hi=170.0, unit="deg", doc="horizontal field of view")
    decimation: int = param(2, lo=1, hi=16, doc="render this many times smaller (binning)")
    oracle_centroid_noise_m: float = param(
        0.001, lo=0.0, hi=0.05, unit="m", doc="oracle: centroid noise std per axis"
    )
    oracle_normal_noise_deg: float = param(
        1.0, lo=0.0, hi=45.0, unit="deg", doc="oracle: normal noise std"
    )
    oracle_range_m: float = param(
        0.0,
        lo=0.0,
        hi=2.0,
        unit="m",
        doc="oracle: sees surfaces within this of the HIP centre (0: perception's workspace)",
    )
    noise: DepthNoiseConfig = nested(DepthNoiseConfig)

    def check(self) -> None:
        if not self.name:
            raise ConfigError("name: must not be empty")
        _need3(self.target_m, "target_m", optional=True)
        if self.placement == "custom":
            _need3(self.position_m, "position_m")
        elif self.position_m:
            raise ConfigError(f"position_m: only with placement = 'custom' (is {self.placement!r})")


@dataclass(frozen=True)
class BodySpec(StageConfig):
    """One ``[[bodies]]`` (or ``[[background]]``) entry: an analytic solid."""

    name: str = param("body", doc="unique name")
    type: str = param("sphere", choices=BODY_TYPES, doc="shape")
    part: str = param("skull_forehead", choices=BODY_PARTS, doc="ISO/TS 15066 body part")
    center_m: tuple[float, ...] = param((), lo=-10.0, hi=10.0, unit="m", doc="centre")
    radius_m: float = param(0.0, lo=0.0, hi=5.0, unit="m", doc="sphere/capsule/cylinder radius")
    semi_axes_m: tuple[float, ...] = param(
        (), lo=0.0, hi=5.0, lo_open=True, unit="m", doc="ellipsoid semi-axes (own frame)"
    )
    a_m: tuple[float, ...] = param((), lo=-10.0, hi=10.0, unit="m", doc="capsule/cylinder end a")
    b_m: tuple[float, ...] = param((), lo=-10.0, hi=10.0, unit="m", doc="capsule/cylinder end b")
    half_extents_m: tuple[float, ...] = param(
        (), lo=0.0, hi=10.0, lo_open=True, unit="m", doc="box half sizes (own frame)"
    )
    rotation_deg: tuple[float, ...] = param(
        (0.0, 0.0, 0.0), lo=-360.0, hi=360.0, unit="deg", doc="own frame: Rz Ry Rx angles"
    )
    velocity_mps: tuple[float, ...] = param(
        (0.0, 0.0, 0.0), lo=-10.0, hi=10.0, unit="m/s", doc="constant velocity while moving"
    )
    motion_start_s: float = param(0.0, lo=0.0, hi=600.0, unit="s", doc="moving from this time")
    motion_duration_s: float = param(
        0.0, lo=0.0, hi=600.0, unit="s", doc="moving this long (0: until the end)"
    )

    def check(self) -> None:
        if not self.name:
            raise ConfigError("name: must not be empty")
        for key in BODY_KEYS[self.type]:
            value = getattr(self, key)
            if key == "radius_m":
                if not value > 0.0:
                    raise ConfigError(f"radius_m: a {self.type} needs radius_m > 0")
            else:
                if not value:
                    raise ConfigError(f"{key}: a {self.type} needs it")
                _need3(value, key)
        _need3(self.rotation_deg, "rotation_deg")
        _need3(self.velocity_mps, "velocity_mps")


@dataclass(frozen=True)
class SurfaceSpec(StageConfig):
    """``[surface]``: a flat plate moving at constant speed towards the HIP (paper Fig. 12).

    The plate is centred on the line through the initial HIP along ``direction``; its face starts
    ``start_gap_m`` from the HIP sphere (free distance), then moves along ``direction`` at
    ``speed_mps`` for ``travel_m``, from ``start_s``.
    """

    name: str = param("surface", doc="body name")
    part: str = param("hand", choices=BODY_PARTS, doc="ISO/TS 15066 body part")
    speed_mps: float = param(
        1.0, lo=0.0, hi=10.0, lo_open=True, unit="m/s", doc="speed towards the HIP"
    )
    direction: tuple[float, ...] = param(
        (0.0, 0.0, 1.0), lo=-1.0, hi=1.0, doc="motion direction = the face's normal (unit)"
    )
    start_gap_m: float = param(
        0.3, lo=0.0, hi=2.0, unit="m", doc="free distance from the HIP sphere at t = 0"
    )
    start_s: float = param(0.0, lo=0.0, hi=600.0, unit="s", doc="starts moving at this time")
    travel_m: float = param(0.4, lo=0.0, hi=5.0, lo_open=True, unit="m", doc="distance moved")
    half_extents_m: tuple[float, ...] = param(
        (0.2, 0.2, 0.02),
        lo=0.001,
        hi=5.0,
        unit="m",
        doc="plate half sizes (the last one along direction)",
    )

    def check(self) -> None:
        _need3(self.direction, "direction")
        _nonzero(self.direction, "direction")
        _need3(self.half_extents_m, "half_extents_m")


@dataclass(frozen=True)
class WallSpec(StageConfig):
    """One ``[[walls]]`` entry: a virtual plane (point + normal to the allowed side)."""

    name: str = param("wall", doc="name")
    point_m: tuple[float, ...] = param((), lo=-10.0, hi=10.0, unit="m", doc="a point of the plane")
    normal: tuple[float, ...] = param((), lo=-1e3, hi=1e3, doc="normal to the allowed side")
    level: str = param(
        "haptic",
        choices=("haptic", "fixed"),
        doc="haptic: the level-4 constraints (Fig. 11); fixed: the level-3 wall",
    )
    part: str = param("", doc="ISO/TS 15066 region for the force limit ('' = default)")

    def check(self) -> None:
        _need3(self.point_m, "point_m")
        _need3(self.normal, "normal")
        _nonzero(self.normal, "normal")
        if self.part:
            try:
                body_region(self.part)
            except ConfigError as err:
                raise ConfigError(f"part = {self.part!r}: {err}") from None


@dataclass(frozen=True)
class WaypointSpec(StageConfig):
    """One ``[[patient.waypoints]]`` entry of the intent script."""

    position_m: tuple[float, ...] = param(
        (), lo=-10.0, hi=10.0, unit="m", doc="intended HIP position (frame: patient.frame)"
    )
    t_s: float = param(-1.0, lo=-1.0, hi=600.0, unit="s", doc="arrival time (-1: from speed)")
    speed_mps: float = param(
        0.0, lo=0.0, hi=10.0, unit="m/s", doc="arrive at this speed (linear: constant)"
    )
    hold_s: float = param(0.0, lo=0.0, hi=600.0, unit="s", doc="stay this long after arriving")
    profile: str = param("min_jerk", choices=PROFILES, doc="time law of the segment to here")

    def check(self) -> None:
        _need3(self.position_m, "position_m")
        if self.t_s >= 0.0 and self.speed_mps > 0.0:
            raise ConfigError("t_s, speed_mps: give one of them, not both")


@dataclass(frozen=True)
class PatientSpec(StageConfig):
    """``[patient]``: the arm that holds the handle (see :mod:`hapticloud.core.sim.patient`)."""

    mass_kg: float = param(1.5, lo=0.0, hi=20.0, unit="kg", doc="hand + forearm mass at the HIP")
    stiffness_n_per_m: float = param(
        300.0, lo=0.0, hi=1e5, unit="N/m", doc="muscle stiffness towards the intent"
    )
    damping_n_s_per_m: float = param(
        25.0, lo=0.0, hi=1e4, unit="N s/m", doc="muscle damping towards the intent's velocity"
    )
    posture_stiffness_nm_per_rad: float = param(
        2.0, lo=0.0, hi=1e3, unit="N m/rad", doc="null-space posture spring"
    )
    posture_damping_nms_per_rad: float = param(
        0.5, lo=0.0, hi=1e3, unit="N m s/rad", doc="null-space posture damping"
    )
    frame: str = param(
        "hip0", choices=("hip0", "world"), doc="waypoints relative to the initial HIP, or world"
    )
    repeat_s: float = param(
        0.0,
        lo=0.0,
        hi=3600.0,
        unit="s",
        doc="play the waypoints again every this many seconds, from the first one's time (0: "
        "once, then hold the last); the last waypoint must return to the first",
    )


@dataclass(frozen=True)
class SceneConfig(StageConfig):
    """Every fixed table of a scene file (the lists are parsed beside it)."""

    scene: SceneMeta = nested(SceneMeta)
    robot: RobotSpec = nested(RobotSpec)
    loop: LoopSpec = nested(LoopSpec)
    patient: PatientSpec = nested(PatientSpec)
    surface: SurfaceSpec = nested(SurfaceSpec)
    perception: PerceptionConfig = nested(PerceptionConfig)
    fusion: FusionConfig = nested(FusionConfig)
    haptics: HapticsConfig = nested(HapticsConfig)
    controller: ControllerConfig = nested(ControllerConfig)

    #: Tables that declare something (built only when present in the file).
    OPTIONAL_TABLES: ClassVar[tuple[str, ...]] = ("patient", "surface")


__all__ = [
    "BODY_KEYS",
    "BODY_TYPES",
    "CAMERA_MODELS",
    "PLACEMENTS",
    "BodySpec",
    "CameraSpec",
    "LoopSpec",
    "PatientSpec",
    "RobotSpec",
    "SceneConfig",
    "SceneMeta",
    "SurfaceSpec",
    "WallSpec",
    "WaypointSpec",
]
