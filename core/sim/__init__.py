"""The simulator: analytic patient bodies, a room, and simulated D435 depth cameras.

Everything here is deterministic given its inputs (noise is seeded by seed, camera name and time)
and is what the ``simulated`` camera source, the tests and the perception benchmark render from.
"""

from .bodies import (
    BODY_PARTS,
    MESH_TOLERANCE_M,
    Body,
    BoxBody,
    CapsuleBody,
    CylinderBody,
    EllipsoidBody,
    SphereBody,
    SurfacePoint,
)
from .depth_camera import RayHits, SimDepthCamera, decimated
from .ellipsoid import closest_point_on_ellipsoid
from .noise import DepthNoiseConfig, apply_depth_noise, frame_key
from .scenes import (
    PLACEMENT_YAW_DEG,
    BenchScene,
    ContactScene,
    HipSamples,
    SimScene,
    contact_bench_scenes,
    demo_scene,
    end_effector,
    finger_on_chest_scene,
    paper_cameras,
    perception_bench_scenes,
    placement_eye,
    rotation_xyz,
    step_bench_scenes,
)
from .world import MISS, OCCLUDER, GroundTruth, SimWorld, intersect_primitive

__all__ = [
    "BODY_PARTS",
    "MESH_TOLERANCE_M",
    "MISS",
    "OCCLUDER",
    "PLACEMENT_YAW_DEG",
    "BenchScene",
    "Body",
    "BoxBody",
    "CapsuleBody",
    "ContactScene",
    "CylinderBody",
    "DepthNoiseConfig",
    "EllipsoidBody",
    "GroundTruth",
    "HipSamples",
    "RayHits",
    "SimDepthCamera",
    "SimScene",
    "SimWorld",
    "SphereBody",
    "SurfacePoint",
    "apply_depth_noise",
    "closest_point_on_ellipsoid",
    "contact_bench_scenes",
    "decimated",
    "demo_scene",
    "end_effector",
    "finger_on_chest_scene",
    "frame_key",
    "intersect_primitive",
    "paper_cameras",
    "perception_bench_scenes",
    "placement_eye",
    "rotation_xyz",
    "step_bench_scenes",
]
