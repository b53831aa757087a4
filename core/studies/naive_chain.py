"""The straightforward Open3D chain, kept only as the speed reference of the benchmark.

Two variants, both measured side by side with :class:`~hapticloud.core.perception.CameraPipeline`
on the same world-frame array:

- ``crop_first=False``, the chain as the issue describes it: the whole frame into an Open3D
  cloud, voxel it whole, crop the workspace sphere, DBSCAN, ICP of the whole memory with a 20 mm
  range, the paper's fixed shells. At our 3.5 mm voxel the whole-frame voxel step alone (about
  326k voxels of room) dominates; the issue measured 32-37 ms for its version of this chain.
- ``crop_first=True``: the same calls with Open3D's box crop first: what a careful first
  implementation would do; the fair reference for what our own stages add.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from ..perception.abstraction import AbstractionConfig, SurfaceFit, estimate_surface

FloatArray = NDArray[np.float64]
_REG = o3d.pipelines.registration


class NaiveOpen3DChain:
    """Open3D all the way, as the paper describes it, without the fast paths."""

    def __init__(
        self,
        voxel_size_m: float = 0.0035,
        workspace_radius_m: float = 0.15,
        r_in_m: float = 0.04,
        r_out_m: float = 0.075,
        dbscan_eps_m: float = 0.008,
        min_cluster_points: int = 20,
        crop_first: bool = True,
    ) -> None:
        self.crop_first = crop_first
        self.voxel_size_m = voxel_size_m
        self.workspace_radius_m = workspace_radius_m
        self.r_in_m = r_in_m
        self.r_out_m = r_out_m
        self.dbscan_eps_m = dbscan_eps_m
        self.min_cluster_points = min_cluster_points
        self.abstraction = AbstractionConfig(method="paper", shell_mode="fixed")
        self._memory: FloatArray | None = None

    def process(
        self, points_world: FloatArray, hip: FloatArray, camera_axis: FloatArray
    ) -> SurfaceFit:
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_world))
        if self.crop_first:
            reach = np.full(3, self.workspace_radius_m)
            cloud = cloud.crop(o3d.geometry.AxisAlignedBoundingBox(hip - reach, hip + reach))
        else:
            cloud = cloud.voxel_down_sample(self.voxel_size_m)
        pts = np.asarray(cloud.points)
        near = np.linalg.norm(pts - hip, axis=1) < self.workspace_radius_m
        cloud = cloud.select_by_index(np.flatnonzero(near).tolist())
        if self.crop_first:
            cloud = cloud.voxel_down_sample(self.voxel_size_m)
        labels = np.asarray(cloud.cluster_dbscan(self.dbscan_eps_m, 1))
        pts = np.asarray(cloud.points)
        if labels.size:
            sizes = np.bincount(labels[labels >= 0]) if (labels >= 0).any() else np.zeros(0)
            big = np.flatnonzero(sizes >= self.min_cluster_points)
            pts = pts[np.isin(labels, big)]
        dist = np.linalg.norm(pts - hip, axis=1)
        ring = pts[(dist >= self.r_in_m) & (dist < self.r_out_m)]
        filled = np.empty((0, 3))
        if self._memory is not None and len(self._memory) >= 3 and len(ring) >= 3:
            source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self._memory))
            target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ring))
            reg = _REG.registration_icp(
                source,
                target,
                0.02,
                np.eye(4),
                _REG.TransformationEstimationPointToPoint(),
                _REG.ICPConvergenceCriteria(max_iteration=30),
            )
            source.transform(reg.transformation)
            moved = np.asarray(source.points)
            filled = moved[np.linalg.norm(moved - hip, axis=1) < self.r_in_m]
        self._memory = np.vstack((ring, filled))
        return estimate_surface(np.vstack((pts, filled)), hip, camera_axis, self.abstraction)
