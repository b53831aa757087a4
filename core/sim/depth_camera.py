"""A simulated Intel RealSense D435 depth camera: ray-cast ideal depth plus a D435-like noise model.

Each pixel's ray is ``(x/z, y/z, 1)`` in the camera frame (OpenCV convention) rotated to the world,
so the ray parameter of a hit *is* the depth along the viewing axis. The patient's bodies and the
room are ray-cast with Open3D on cached BVHs (:class:`~hapticloud.core.sim.world.SimWorld`); the
robot's primitives, which change every frame, are intersected in closed form over the pixels their
bounding box covers, then merged by minimum depth.

A frame for the perception need not be ray-cast whole: stage A (the crop,
:func:`~hapticloud.core.perception.crop.crop_depth_frame`) only reads the pixels of the workspace
sphere's rectangle. :meth:`SimDepthCamera.workspace_roi` computes that rectangle with the crop's
own :func:`~hapticloud.core.perception.crop.sphere_region` (plus a margin), and
``render(..., roi=...)`` ray-casts only it (plus the noise model's neighbours) and returns a
full-size frame that is 0 (invalid) outside it and bit for bit the full render inside it (the
noise is keyed per pixel, :mod:`.noise`). Pixels left out read as invalid, never as free space:
a ROI too small would make the crop see less, not see emptiness.

Example
-------
>>> from hapticloud.core.camera import CameraIntrinsics, look_at
>>> from hapticloud.core.sim.bodies import SphereBody
>>> from hapticloud.core.sim.world import SimWorld
>>> world = SimWorld([SphereBody(name="head", part="skull_forehead", center=[0, 0, 1.2],
...                              radius_m=0.09)])
>>> cam = SimDepthCamera("front", CameraIntrinsics.d435(), look_at([0.8, 0, 1.2], [0, 0, 1.2]))
>>> frame = cam.render(world, t=0.0)
>>> frame.depth_m.shape, frame.depth_m.dtype.name
((480, 848), 'float32')
"""

from __future__ import annotations

import operator
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..camera import CameraIntrinsics, DepthFrame
from ..errors import InputError
from ..geometry.primitives import Primitive
from ..perception.crop import CropConfig, sphere_region
from ..validation import as_finite_scalar
from .noise import NOISE_MARGIN_PX, DepthNoiseConfig, apply_depth_noise, frame_key
from .raygrid import RayGrid, Window, intersect_windows
from .world import MISS, OCCLUDER, SimWorld

__all__ = [
    "EMPTY_ROI",
    "MISS",
    "OCCLUDER",
    "ROI_MARGIN_PX",
    "DepthNoiseConfig",
    "RayHits",
    "SimDepthCamera",
    "Window",
    "decimated",
]

FloatArray = NDArray[np.float64]

#: Pixels added on every side of the crop's rectangle by :meth:`SimDepthCamera.workspace_roi`:
#: slack for a HIP or crop radius a rounding away from the ones the ROI was computed with (the
#: rectangle itself already has one pixel of slack for rounding).
ROI_MARGIN_PX = 2
#: The empty region of interest: nothing of the workspace is in view, nothing is cast.
EMPTY_ROI: Window = (0, 0, 0, 0)


@dataclass(frozen=True)
class RayHits:
    """What a camera's rays saw, before sensor noise.

    ``depth_m`` (H, W) float32 depth along the camera axis, ``inf`` where nothing was hit;
    ``label`` (H, W) int32: index into ``world.surfaces``, :data:`MISS` or :data:`OCCLUDER`;
    ``cos_incidence`` (H, W) float32 ``|cos|`` of the angle between ray and surface normal
    (1 head-on, 0 grazing, 0 on a miss), or None when not asked for.
    """

    depth_m: NDArray[np.float32]
    label: NDArray[np.int32]
    cos_incidence: NDArray[np.float32] | None


def decimated(intrinsics: CameraIntrinsics, factor: int) -> CameraIntrinsics:
    """Intrinsics of the image binned by ``factor`` (the D435's decimation filter geometry)."""
    if factor == 1:
        return intrinsics
    k = intrinsics
    return CameraIntrinsics(
        k.width // factor,
        k.height // factor,
        k.fx / factor,
        k.fy / factor,
        (k.cx + 0.5) / factor - 0.5,
        (k.cy + 0.5) / factor - 0.5,
    )


def _rigid_pose(pose: ArrayLike) -> FloatArray:
    arr = np.array(pose, dtype=np.float64)
    if arr.shape != (4, 4) or not np.all(np.isfinite(arr)):
        raise InputError(
            f"pose_world_camera: expected a finite 4x4 transform, got shape {arr.shape}"
        )
    rot = arr[:3, :3]
    if (
        not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6)
        or np.linalg.det(rot) < 0
        or not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0])
    ):
        raise InputError(
            "pose_world_camera: must be a rigid transform (rotation, det +1; last row 0 0 0 1)"
        )
    arr.setflags(write=False)
    return arr


class SimDepthCamera:
    """A simulated depth camera at a fixed pose.

    Parameters
    ----------
    name
        Camera name (stamped on frames; part of the noise seed).
    intrinsics
        Full-resolution pin-hole intrinsics (``CameraIntrinsics.d435()`` for 848x480).
    pose_world_camera
        4x4 rigid transform camera -> world.
    noise
        Noise model; ``DepthNoiseConfig()`` (D435-like) by default.
    decimation
        Render a ``decimation`` times smaller image (1: full resolution).
    """

    def __init__(
        self,
        name: str,
        intrinsics: CameraIntrinsics,
        pose_world_camera: ArrayLike,
        noise: DepthNoiseConfig | None = None,
        *,
        decimation: int = 1,
    ) -> None:
        if not isinstance(name, str) or not name:
            raise InputError(f"name: expected a non-empty string, got {name!r}")
        if not isinstance(intrinsics, CameraIntrinsics):
            raise InputError(
                f"intrinsics: expected CameraIntrinsics, got {type(intrinsics).__name__}"
            )
        if (
            isinstance(decimation, bool)
            or not isinstance(decimation, int)
            or not (1 <= decimation <= 16)
        ):
            raise InputError(f"decimation = {decimation!r}: expected an integer in [1, 16]")
        if noise is not None and not isinstance(noise, DepthNoiseConfig):
            raise InputError(f"noise: expected DepthNoiseConfig, got {type(noise).__name__}")
        self._name = name
        self._k = decimated(intrinsics, decimation)
        self._pose = _rigid_pose(pose_world_camera)
        self._noise = noise if noise is not None else DepthNoiseConfig()
        self._decimation = decimation
        self._grid: RayGrid | None = None
        self._inv_len: NDArray[np.float32] | None = None

    # ----- description -------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self._name

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """Intrinsics of the rendered image (after decimation)."""
        return self._k

    @property
    def decimation(self) -> int:
        """Binning factor from the full-resolution intrinsics given at construction."""
        return self._decimation

    @property
    def pose_world_camera(self) -> FloatArray:
        return self._pose

    @property
    def noise(self) -> DepthNoiseConfig:
        return self._noise

    @property
    def origin_world(self) -> FloatArray:
        """Optical centre in the world, m."""
        return self._pose[:3, 3].copy()

    @property
    def axis_world(self) -> FloatArray:
        """Viewing axis (camera z) in the world."""
        return self._pose[:3, 2].copy()

    def with_noise(self, noise: DepthNoiseConfig) -> SimDepthCamera:
        """The same camera with another noise model (shares no mutable state)."""
        return SimDepthCamera(self._name, self._k, self._pose, noise)

    def project(self, points_world: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Pixel coordinates ``(u, v)`` (column, row) and depth ``z`` (m) of world points.

        Returns ``(uv (N, 2), z (N,))``; ``uv`` is NaN for points at or behind the camera plane.
        """
        p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        pc = (p - self._pose[:3, 3]) @ self._pose[:3, :3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.column_stack(
                (self._k.fx * pc[:, 0] / z + self._k.cx, self._k.fy * pc[:, 1] / z + self._k.cy)
            )
        uv[~(z > 1e-9)] = np.nan
        return uv, z

    # ----- region of interest ----------------------------------------------------------------
    def workspace_roi(
        self,
        hip: ArrayLike,
        crop: CropConfig | None = None,
        *,
        margin_px: int = ROI_MARGIN_PX,
    ) -> Window:
        """The pixels a perception crop around ``hip`` reads, as a ``render`` ROI.

        The rectangle of :func:`~hapticloud.core.perception.crop.sphere_region` (the very
        function stage A uses) for the workspace sphere of ``crop`` (``CropConfig()`` if None:
        radius and valid depth range) around ``hip`` (m, world), grown by ``margin_px`` on every
        side and clipped to the image: ``(row0, row1, col0, col1)``, half-open, in the rendered
        (decimated) image. :data:`EMPTY_ROI` when the sphere is out of view (the crop then finds
        nothing either).
        """
        cfg = crop if crop is not None else CropConfig()
        if isinstance(margin_px, bool) or not isinstance(margin_px, int) or margin_px < 0:
            raise InputError(f"margin_px = {margin_px!r}: expected an integer >= 0")
        k = self._k
        # sphere_region reads only the frame's pose and intrinsics: a zero-stride depth image
        # gives it a frame without allocating one.
        probe = DepthFrame(
            0.0, self._name, np.broadcast_to(np.float32(0.0), (k.height, k.width)), k, self._pose
        )
        found = sphere_region(probe, hip, cfg.workspace_radius_m, cfg.min_depth_m, cfg.max_depth_m)
        if found is None:
            return EMPTY_ROI
        row0, row1, col0, col1 = found[:4]
        return (
            max(0, row0 - margin_px),
            min(k.height, row1 + margin_px),
            max(0, col0 - margin_px),
            min(k.width, col1 + margin_px),
        )

    def _checked_roi(self, roi: ArrayLike) -> Window:
        try:
            r0, r1, c0, c1 = (operator.index(v) for v in roi)  # type: ignore[union-attr]
        except (TypeError, ValueError):
            raise InputError(
                f"roi = {roi!r}: expected (row0, row1, col0, col1), four integers"
            ) from None
        k = self._k
        if not (0 <= r0 <= r1 <= k.height and 0 <= c0 <= c1 <= k.width):
            raise InputError(
                f"roi = {roi!r}: expected 0 <= row0 <= row1 <= {k.height} and "
                f"0 <= col0 <= col1 <= {k.width}"
            )
        return r0, r1, c0, c1

    # ----- rays --------------------------------------------------------------------------------
    def _ray_grid(self) -> RayGrid:
        if self._grid is None:
            xs, ys = self._k.pixel_rays()
            local = np.stack((xs, ys, np.ones_like(xs)), axis=-1).astype(np.float64)
            dirs = (local @ self._pose[:3, :3].T).astype(np.float32)
            inv_len = (1.0 / np.linalg.norm(local, axis=-1)).astype(np.float32)
            dirs.setflags(write=False)
            inv_len.setflags(write=False)
            self._grid = RayGrid(self._pose[:3, 3], dirs, self.project)
            self._inv_len = inv_len
        return self._grid

    # ----- rendering ---------------------------------------------------------------------------
    def trace(
        self,
        world: SimWorld,
        t: float = 0.0,
        occluders: Sequence[Primitive] = (),
        *,
        incidence: bool = False,
        roi: Window | None = None,
    ) -> RayHits:
        """Ideal hits of every pixel at time ``t`` (s), with labels (and incidence if asked).

        With ``roi`` ``(row0, row1, col0, col1)`` only those pixels are cast and the arrays
        have the ROI's shape.
        """
        if not isinstance(world, SimWorld):
            raise InputError(f"world: expected SimWorld, got {type(world).__name__}")
        grid = self._ray_grid()
        t = as_finite_scalar(t, "t")
        if roi is not None:
            roi = self._checked_roi(roi)
        depth, label, normals = world.trace(
            grid, t, tuple(occluders), want_normals=incidence, roi=roi
        )
        cos_inc = None
        if normals is not None:
            assert self._inv_len is not None  # set with the directions
            r0, r1, c0, c1 = roi if roi is not None else (0, grid.shape[0], 0, grid.shape[1])
            d = grid.directions[r0:r1, c0:c1]
            # Component-wise, not einsum: a pixel's value must not depend on the array's extent.
            dot = normals[..., 0] * d[..., 0] + normals[..., 1] * d[..., 1]
            dot += normals[..., 2] * d[..., 2]
            cos_inc = np.abs(dot) * self._inv_len[r0:r1, c0:c1]
            np.minimum(cos_inc, 1.0, out=cos_inc)
        return RayHits(depth, label, cos_inc)

    def ideal_depth(
        self, world: SimWorld, t: float = 0.0, occluders: Sequence[Primitive] = ()
    ) -> NDArray[np.float32]:
        """Noise-free depth image ``(H, W)`` float32 in m, 0 where nothing was hit."""
        depth = self.trace(world, t, occluders).depth_m
        depth[~np.isfinite(depth)] = 0.0
        return depth

    def render(
        self,
        world: SimWorld,
        t: float = 0.0,
        occluders: Sequence[Primitive] = (),
        roi: Window | None = None,
    ) -> DepthFrame:
        """One noisy depth frame at time ``t`` (s); deterministic in (seed, name, t, scene).

        ``roi`` ``(row0, row1, col0, col1)`` (half-open, in the rendered image; e.g. from
        :meth:`workspace_roi`): ray-cast only those pixels (and :data:`~.noise.NOISE_MARGIN_PX`
        around them for the noise model) and return a full-size frame that is 0 (invalid)
        outside the ROI and the same as the full render, bit for bit, inside it. An empty ROI
        casts nothing: an all-invalid frame.
        """
        cfg = self._noise
        grazing = cfg.grazing_dropout > 0 and cfg.grazing_start_deg < 90.0
        t = as_finite_scalar(t, "t")
        key = frame_key(cfg.seed, self._name, t)
        k = self._k
        if roi is None:
            hits = self.trace(world, t, occluders, incidence=grazing)
            depth = apply_depth_noise(hits.depth_m, cfg, key, hits.cos_incidence)
            return DepthFrame(t, self._name, depth, k, self._pose.copy())
        r0, r1, c0, c1 = self._checked_roi(roi)
        depth = np.zeros((k.height, k.width), dtype=np.float32)
        if r0 < r1 and c0 < c1:
            m = NOISE_MARGIN_PX
            cast = intersect_windows((r0 - m, r1 + m, c0 - m, c1 + m), (0, k.height, 0, k.width))
            assert cast is not None  # it holds the non-empty ROI
            hits = self.trace(world, t, occluders, incidence=grazing, roi=cast)
            noisy = apply_depth_noise(
                hits.depth_m,
                cfg,
                key,
                hits.cos_incidence,
                origin=(cast[0], cast[2]),
                image_width=k.width,
            )
            depth[r0:r1, c0:c1] = noisy[r0 - cast[0] : r1 - cast[0], c0 - cast[2] : c1 - cast[2]]
        elif not isinstance(world, SimWorld):
            raise InputError(f"world: expected SimWorld, got {type(world).__name__}")
        return DepthFrame(t, self._name, depth, k, self._pose.copy())

    def render_points(
        self, world: SimWorld, t: float = 0.0, occluders: Sequence[Primitive] = ()
    ) -> FloatArray:
        """A rendered frame's valid pixels as ``(N, 3)`` world points, m (the full-cloud path)."""
        return self.render(world, t, occluders).points_world()
