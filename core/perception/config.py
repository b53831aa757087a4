"""All perception parameters of one camera: one table per stage (A-E)."""

from __future__ import annotations

from dataclasses import dataclass

from ..config import StageConfig, nested, param
from ..errors import ConfigError
from .abstraction import AbstractionConfig
from .cluster import ClusterConfig
from .crop import CropConfig
from .reconstruct import ReconstructionConfig
from .voxel import VoxelConfig


@dataclass(frozen=True)
class PerceptionConfig(StageConfig):
    """Parameters of :class:`~hapticloud.core.perception.CameraPipeline`.

    The shipped defaults are the tuned ones (``docs/benchmarks.md`` has the study behind them).
    Stage tables: ``crop`` (A), ``voxel`` (B), ``cluster`` (C), ``reconstruction`` (D, the ICP
    memory ring), ``abstraction`` (E, the surface estimator).
    """

    crop: CropConfig = nested(CropConfig)
    voxel: VoxelConfig = nested(VoxelConfig)
    cluster: ClusterConfig = nested(ClusterConfig)
    reconstruction: ReconstructionConfig = nested(ReconstructionConfig)
    abstraction: AbstractionConfig = nested(AbstractionConfig)
    keep_points: bool = param(
        True, doc="attach the kept and filled points to each estimate (for the app; costs copies)"
    )
    max_spacing_m: float = param(
        0.010,
        lo=0.001,
        hi=0.1,
        unit="m",
        doc="coarser sampling than this (voxel or camera pixels at the HIP): estimate invalid",
    )
    supported_gap_m: float = param(
        0.008,
        lo=0.001,
        hi=0.2,
        unit="m",
        doc="closest point within this (or the point spacing) of a point it was fitted to: "
        "supported as it is",
    )
    max_support_gap_m: float = param(
        0.03,
        lo=0.001,
        hi=0.2,
        unit="m",
        doc="closest point farther than this from every point it was fitted to (and not "
        "surrounded by them): invalid",
    )
    extrapolation_margin: float = param(
        0.15,
        lo=0.0,
        hi=2.0,
        doc="an extrapolated closest point is moved toward the HIP by this x its gap beyond "
        "supported_gap_m (what is not seen is taken as nearer)",
    )
    extrapolation_sigmas: float = param(
        0.0,
        lo=0.0,
        hi=20.0,
        doc="instead (> 0), a fitted surface's extrapolated closest point is moved toward the HIP "
        "by this many standard errors of the fitted height there: at 4 no repeated demo press "
        "entered the cheek, but presses bounce (docs/benchmarks.md)",
    )
    min_seen_fraction: float = param(
        0.9,
        lo=0.0,
        hi=1.0,
        doc="empty workspace counts as free only if this share of its pixels was seen",
    )

    def check(self) -> None:
        if self.voxel.voxel_size_m > self.max_spacing_m:
            raise ConfigError(
                f"voxel.voxel_size_m = {self.voxel.voxel_size_m}: coarser than max_spacing_m = "
                f"{self.max_spacing_m}, so no estimate could be trusted"
            )
        workspace = self.crop.workspace_radius_m
        for name, radius in (
            ("abstraction.r_out_m", self.abstraction.r_out_m),
            ("reconstruction.r_out_m", self.reconstruction.r_out_m),
        ):
            if radius > workspace + 1e-12:
                raise ConfigError(
                    f"{name} = {radius}: must not exceed crop.workspace_radius_m = {workspace}"
                    " (points beyond the workspace are never seen)"
                )
