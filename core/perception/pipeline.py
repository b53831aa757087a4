"""One camera's perception pipeline: stages A-E from a cloud or a depth frame to an estimate."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..camera import DepthFrame
from ..errors import InputError
from ..geometry.primitives import Primitive
from ..validation import as_finite_scalar, as_unit_vector3, as_vector3
from .abstraction import estimate_surface
from .cluster import adapted_to_spacing, cluster_voxels
from .config import PerceptionConfig
from .crop import HIDDEN_STEP_M, CropResult, crop_depth_frame, crop_points, hidden_length
from .estimate import SurfaceEstimate
from .reconstruct import SurfaceMemory
from .timing import StageTimer
from .voxel import voxel_downsample

FloatArray = NDArray[np.float64]

STAGES = ("crop", "voxel", "cluster", "rebuild", "abstract")


class CameraPipeline:
    """Stages A-E for one camera; keeps that camera's ICP memory between frames.

    Parameters
    ----------
    config
        All stage parameters; the shipped defaults are the tuned ones.
    camera
        Name carried into every :class:`SurfaceEstimate`.

    Examples
    --------
    >>> import numpy as np
    >>> from hapticloud.core.perception import CameraPipeline, PerceptionConfig
    >>> rng = np.random.default_rng(0)
    >>> xy = rng.uniform(-0.12, 0.12, size=(20000, 2))
    >>> wall = np.column_stack((xy, np.zeros(len(xy))))          # the plane z = 0
    >>> pipe = CameraPipeline(PerceptionConfig())
    >>> est = pipe.process(wall, hip=[0.0, 0.0, 0.06], camera_axis=[0.0, 0.0, -1.0], t=0.0)
    >>> est.valid, bool(abs(est.d_proj([0.0, 0.0, 0.06], 0.04) - 0.02) < 1e-3)
    (True, True)
    """

    def __init__(self, config: PerceptionConfig | None = None, camera: str = "camera") -> None:
        self._config = PerceptionConfig() if config is None else config
        if not isinstance(self._config, PerceptionConfig):
            raise InputError(f"config: expected a PerceptionConfig, got {type(config).__name__}")
        self.camera = str(camera)
        self._memory = SurfaceMemory(self._config.reconstruction)
        self._seq = 0

    @property
    def config(self) -> PerceptionConfig:
        return self._config

    def configure(self, config: PerceptionConfig) -> None:
        """Use ``config`` from the next frame on (the memory restarts if its stage changed)."""
        if not isinstance(config, PerceptionConfig):
            raise InputError(f"config: expected a PerceptionConfig, got {type(config).__name__}")
        if config.reconstruction != self._config.reconstruction:
            self._memory = SurfaceMemory(config.reconstruction)
        self._config = config

    def reset(self) -> None:
        """Forget the ICP memory (after a seek in a recording or a recalibration)."""
        self._memory.reset()

    # ----- entry points --------------------------------------------------------------------------
    def process(
        self,
        points_world: ArrayLike,
        hip: ArrayLike,
        camera_axis: ArrayLike,
        t: float = 0.0,
        exclude: Sequence[Primitive] | None = (),
    ) -> SurfaceEstimate:
        """Estimate the surface closest to ``hip`` from a world-frame cloud.

        Parameters
        ----------
        points_world
            ``(N, 3)`` points in the world frame (m), float32 or float64 (a full frame of ~400k
            points is fine: stage A crops it first). NaN/inf rows are dropped.
        hip
            ``(3,)`` haptic interaction point (m, world).
        camera_axis
            ``(3,)`` the camera's viewing direction (world); orients the normal towards the camera.
        t
            Frame time (s, monotonic).
        exclude
            Primitives (``Sphere``, ``Capsule``, ``Box``) of the robot and the guided arm in the
            world frame; points inside them, grown by ``crop.exclude_margin_m``, are removed.

        Returns
        -------
        SurfaceEstimate
            ``valid`` False (with ``reason``) when the surface cannot be estimated; never NaN.

        Raises
        ------
        InputError
            (a ``ValueError``) naming the argument with a wrong shape, dtype or value.
        """
        h = as_vector3(hip, "hip")
        axis = as_unit_vector3(camera_axis, "camera_axis")
        t = as_finite_scalar(t, "t")
        timer = StageTimer()
        with timer.stage("crop"):
            cropped = crop_points(points_world, h, exclude, self._config.crop)
        return self._finish(cropped, h, axis, t, timer, exclude)

    def process_depth(
        self,
        frame: DepthFrame,
        hip: ArrayLike,
        exclude: Sequence[Primitive] | None = (),
    ) -> SurfaceEstimate:
        """Estimate the surface closest to ``hip`` from one depth frame.

        Stage A works in image space: the workspace sphere is projected into the image and only
        that region is deprojected. The camera axis and time come from the frame.

        Parameters
        ----------
        frame
            Depth image (m; 0 or NaN invalid), intrinsics and ``pose_world_camera``.
        hip, exclude
            As in :meth:`process`.
        """
        if not isinstance(frame, DepthFrame):
            raise InputError(f"frame: expected a DepthFrame, got {type(frame).__name__}")
        h = as_vector3(hip, "hip")
        t = as_finite_scalar(frame.t, "frame.t")
        timer = StageTimer()
        with timer.stage("crop"):
            cropped = crop_depth_frame(frame, h, exclude, self._config.crop)
        return self._finish(cropped, h, frame.axis_world, t, timer, exclude)

    # ----- stages B-E ----------------------------------------------------------------------------
    def _finish(
        self,
        cropped: CropResult,
        h: FloatArray,
        axis: FloatArray,
        t: float,
        timer: StageTimer,
        exclude: Sequence[Primitive] | None,
    ) -> SurfaceEstimate:
        cfg = self._config
        self._seq += 1
        size = cfg.voxel.voxel_size_m
        spacing = max(size, cropped.spacing_m)
        base = {"hip": h, "seq": self._seq, "method": cfg.abstraction.method}
        if spacing > cfg.max_spacing_m:
            # Too coarse to resolve the surface: nothing this frame shows can be trusted.
            reason = (
                f"points {spacing * 1e3:.1f} mm apart at the HIP (voxel or pixel spacing) "
                f"> max_spacing_m {cfg.max_spacing_m * 1e3:.1f} mm: surface not resolved"
            )
            return SurfaceEstimate.invalid(t, self.camera, reason, stage_ms=_ms(timer), **base)
        with timer.stage("voxel"):
            # The grid is anchored on the world lattice (a voxel corner near the HIP), not at the
            # HIP itself: a grid moving with the HIP resamples a still surface every frame and the
            # ICP memory then follows the samples instead of the surface.
            anchor = np.floor(h / size) * size
            voxels = voxel_downsample(cropped.points, anchor, cfg.voxel)
        with timer.stage("cluster"):
            clusters = cluster_voxels(voxels, h, cfg.cluster, cropped.spacing_m)
        with timer.stage("rebuild"):
            rebuilt = self._memory.step(clusters.points, h, t)
        with timer.stage("abstract"):
            fit = estimate_surface(rebuilt.points, h, axis, cfg.abstraction)
            gap = _support_gap(fit.centroid, rebuilt.points) if fit.valid else 0.0
            # Sparser sampling leaves larger gaps between true neighbours: never below spacing.
            supported = max(cfg.supported_gap_m, spacing)
            # A hole (the end effector hides the surface under the HIP) is bridged when the
            # points surround it: that is interpolation, not extrapolation.
            extrapolated = gap > supported and not _surrounded(
                fit.centroid, fit.normal, rebuilt.points, gap
            )
        extra = {
            **base,
            "method": fit.method or cfg.abstraction.method,
            "quality": fit.quality,
            "n_points": int(rebuilt.points.shape[0]),
            "shells": fit.shells,
            "stage_ms": _ms(timer),
            "surfaces": fit.surfaces,
            "note": fit.reason if fit.valid else "",
            "residual_m": fit.residual_m,
        }
        if cfg.keep_points:
            extra["points"] = clusters.points
            extra["filled"] = rebuilt.filled
            extra["rejected"] = clusters.rejected
        centroid = fit.centroid
        if fit.valid and extrapolated:
            if gap > max(cfg.max_support_gap_m, supported):
                reason = (
                    f"closest point {gap * 1e3:.1f} mm from the nearest point it was fitted to "
                    f"> max_support_gap_m {cfg.max_support_gap_m * 1e3:.1f} mm, and not "
                    "surrounded by them"
                )
                return SurfaceEstimate.invalid(t, self.camera, reason, **extra)
            # Extrapolated: what the points do not show is taken as nearer, in proportion to the
            # gap or (extrapolation_sigmas > 0) by the fit's own uncertainty there.
            if cfg.extrapolation_sigmas > 0.0 and fit.height_se_m > 0.0:
                shift = cfg.extrapolation_sigmas * fit.height_se_m
            else:
                shift = cfg.extrapolation_margin * (gap - supported)
            centroid = centroid + shift * fit.normal
        margin = cfg.crop.exclude_margin_m
        if fit.valid:
            # The crop removed what it saw in the robot's grown shapes: a surface there is unseen,
            # and a wide margin around the HIP's ball can swallow the surface nearest to it while
            # the fit bridges the hole from farther points (reporting the surface farther).
            hidden = hidden_length(h, centroid, exclude, margin)
            if hidden > cfg.max_support_gap_m + HIDDEN_STEP_M:
                reason = (
                    f"{hidden * 1e3:.0f} mm of the way from the HIP to the closest point lies in "
                    f"the robot's shapes grown by crop.exclude_margin_m {margin * 1e3:.0f} mm "
                    f"(> max_support_gap_m {cfg.max_support_gap_m * 1e3:.1f} mm): the surface "
                    "there was removed with the robot and may be nearer"
                )
                return SurfaceEstimate.invalid(t, self.camera, reason, **extra)
        if fit.valid and not float((h - centroid) @ fit.normal) > 0.0:
            # Any method: a normal away from the HIP puts the HIP behind the surface (d_proj below
            # -r_hip), and a constraint on that plane would push the HIP toward the body.
            reason = "the estimated normal points away from the HIP (the HIP behind the surface)"
            return SurfaceEstimate.invalid(t, self.camera, reason, **extra)
        if not fit.valid:
            reason = fit.reason
            free = 0.0
            if rebuilt.points.shape[0] == 0 and cropped.region is not None:
                # Nothing that could be a surface in the workspace: free space, if the frame saw
                # the workspace (invalid pixels or something nearer the camera hide it).
                seen = cropped.seen_fraction
                stray = int(clusters.rejected.shape[0])
                _, min_cluster = adapted_to_spacing(cfg.cluster, size, cropped.spacing_m)
                if stray >= min_cluster:
                    reason = f"{stray} points in clusters too small to trust"
                elif cropped.n_robot and margin > cfg.max_support_gap_m:
                    # The grown robot shapes removed what lay in their margin: not seen empty.
                    reason = (
                        f"workspace empty but for {cropped.n_robot} points removed with the "
                        f"robot's shapes grown by crop.exclude_margin_m {margin * 1e3:.0f} mm "
                        f"(> max_support_gap_m {cfg.max_support_gap_m * 1e3:.1f} mm): unknown"
                    )
                elif seen >= cfg.min_seen_fraction:
                    free = cfg.crop.workspace_radius_m
                    reason = "workspace seen empty" + (f" ({stray} stray points)" if stray else "")
                else:
                    reason = (
                        f"workspace {seen:.0%} seen "
                        f"(min_seen_fraction {cfg.min_seen_fraction:.0%}): unknown"
                    )
            elif cropped.n_kept == 0:
                reason = "no points in the workspace sphere"
            elif clusters.points.shape[0] == 0:
                reason = "no cluster large enough"
            return SurfaceEstimate.invalid(t, self.camera, reason, free_m=free, **extra)
        return SurfaceEstimate(
            t=t, camera=self.camera, centroid=centroid, normal=fit.normal, valid=True, **extra
        )


def _ms(timer: StageTimer) -> dict[str, float]:
    stage_ms = dict(timer.ms)
    stage_ms["total"] = timer.total_ms
    return stage_ms


#: A hole counts as surrounded when no angular sector wider than this (rad) around the closest
#: point, in its tangent plane, is empty of points.
MAX_OPEN_SECTOR_RAD = math.radians(120.0)


def _surrounded(centroid: FloatArray, normal: FloatArray, points: FloatArray, gap: float) -> bool:
    """Whether the points within ``2 x gap`` of the closest point (beyond the hole of radius
    ``gap``) lie all around it in the tangent plane: no empty sector wider than 120 deg."""
    d = points - centroid
    near = d[np.einsum("ij,ij->i", d, d) <= 4.0 * gap * gap]
    if near.shape[0] < 8:
        return False
    # Any two tangent directions: the angles' origin does not matter, only their gaps.
    t1 = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(normal, t1)
    angles = np.sort(np.arctan2(near @ t2, near @ t1))
    gaps = np.diff(np.concatenate((angles, [angles[0] + 2.0 * math.pi])))
    return float(gaps.max()) <= MAX_OPEN_SECTOR_RAD


def _support_gap(centroid: FloatArray, points: FloatArray) -> float:
    """Distance (m) from the estimated closest point to the nearest point of the fitted cloud."""
    if points.shape[0] == 0:
        return math.inf
    d = points - centroid
    return math.sqrt(float(np.min(np.einsum("ij,ij->i", d, d))))


def frame_rate_bound_mps(config: PerceptionConfig, frame_period_s: float) -> float:
    """Eq. 1: the largest surface speed along its normal the memory ring can follow (m/s)."""
    if not (math.isfinite(frame_period_s) and frame_period_s > 0):
        raise InputError(f"frame_period_s = {frame_period_s}: must be positive")
    rec = config.reconstruction
    return (rec.r_out_m - rec.r_in_m) / frame_period_s
