"""Scene files: what a session declares (cameras, robot, bodies, walls, patient, parameters).

``load_scene(path, overrides)`` reads a TOML scene file into a validated :class:`Scene`; every
error is a one-line :class:`~hapticloud.core.errors.ConfigError` naming the file and the key.
The tables and their keys are in :mod:`.schema`; ``docs/closed-loop.md`` documents them.
"""

from .loader import LIST_TABLES, Scene, load_scene, parse_scene, resolve_scene, scenes_dir
from .schema import (
    BODY_TYPES,
    CAMERA_MODELS,
    PLACEMENTS,
    BodySpec,
    CameraSpec,
    LoopSpec,
    PatientSpec,
    RobotSpec,
    SceneConfig,
    SceneMeta,
    SurfaceSpec,
    WallSpec,
    WaypointSpec,
)

__all__ = [
    "BODY_TYPES",
    "CAMERA_MODELS",
    "LIST_TABLES",
    "PLACEMENTS",
    "BodySpec",
    "CameraSpec",
    "LoopSpec",
    "PatientSpec",
    "RobotSpec",
    "Scene",
    "SceneConfig",
    "SceneMeta",
    "SurfaceSpec",
    "WallSpec",
    "WaypointSpec",
    "load_scene",
    "parse_scene",
    "resolve_scene",
    "scenes_dir",
]
