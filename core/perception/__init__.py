"""Perception: from one camera's cloud or depth frame to the closest surface point and normal.

Stages, one module each: A :mod:`.crop`, B :mod:`.voxel`, C :mod:`.cluster`,
D :mod:`.reconstruct` (ICP memory ring, Alg. 1), E :mod:`.abstraction` (Alg. 2, and the
curvature-aware estimator in :mod:`.curvature`). :class:`CameraPipeline` runs them in order.
"""

from .abstraction import AbstractionConfig, SurfaceFit, estimate_surface
from .cluster import ClusterConfig
from .config import PerceptionConfig
from .crop import CropConfig
from .estimate import ShellFit, SurfaceEstimate
from .pipeline import STAGES, CameraPipeline, frame_rate_bound_mps
from .reconstruct import ReconstructionConfig, SurfaceMemory
from .voxel import VoxelConfig

__all__ = [
    "STAGES",
    "AbstractionConfig",
    "CameraPipeline",
    "ClusterConfig",
    "CropConfig",
    "PerceptionConfig",
    "ReconstructionConfig",
    "ShellFit",
    "SurfaceEstimate",
    "SurfaceFit",
    "SurfaceMemory",
    "VoxelConfig",
    "estimate_surface",
    "frame_rate_bound_mps",
]
