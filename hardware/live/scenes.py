"""The simulated scenes a live source runs: built-in ones and scene files, with what the view
draws of them (display meshes, cameras, the robot's shapes).

Scene-file scenes are built by the scene's assembly
(:func:`~hapticloud.core.scene.assembly.assemble`, called in :func:`_assembled` only).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from hapticloud.core.errors import ConfigError
from hapticloud.core.geometry.primitives import Box, Capsule, Primitive, Sphere
from hapticloud.core.sim import SimScene, demo_scene, end_effector
from hapticloud.core.studies.demo import DEMO_HANDLE_DIRECTION, hip_at
from hapticloud.core.studies.perception import R_HIP_M
from hapticloud.core.validation import read_only_copy
from numpy.typing import NDArray

from .contract import BodyMesh, CameraInfo, SceneGeometry

FloatArray = NDArray[np.float64]

#: Chord tolerance of the display meshes of the simulator's bodies (m). The ray-casting meshes
#: (0.1 mm, 176k vertices for the demo) are far too heavy to draw at 30 Hz in software GL.
DISPLAY_MESH_TOLERANCE_M = 0.002


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
        over = {f"cameras.{c.name}.decimation": decimation for c in loaded.cameras}
        sim = _assembled(loaded.with_overrides(over) if decimation > 1 else loaded)
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
        return _assembled(loaded)

    def hip_path(t: float) -> FloatArray:
        return read_only_copy(sim().hip0)

    def world_at(t: float) -> Any:
        # The scene's schedule (start, duration) as the closed loop runs it: the moving
        # surface moves in the view and in the simulated cameras too.
        return sim().world.at(t)

    moving = any(np.any(b.velocity_mps) for b in loaded.bodies) or loaded.has_surface
    return SceneSpec(build, hip_path, loaded.config.scene.description, world_at if moving else None)


def _assembled(loaded: Any) -> Any:
    """The loaded scene's world, cameras and robot as the closed loop builds them."""
    from hapticloud.core.scene.assembly import assemble

    return assemble(loaded)


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
