"""One camera's bundle of pixel rays, with the caches that make per-frame ray casting cheap.

Casting all 407k rays of an 848x480 image costs ~14 ms on 2 cores (~28 ms on one), most of a
frame's budget, although the room and a still patient look the same in every frame. A
:class:`RayGrid` therefore keeps, per motion group of the world, the last hits keyed by the
group's shapes and its displacement: a static group is cast once per camera, a moving one only
over the image window its bounding box covers.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
Window = tuple[int, int, int, int]
Projector = Callable[[FloatArray], tuple[FloatArray, FloatArray]]
#: ``(origin_rest, directions, s, position, normals) -> None``: corrects hits in place.
Refiner = Callable[
    [FloatArray, NDArray[np.float32], NDArray[np.float32], NDArray[np.int32], NDArray[np.float32]],
    None,
]

_CACHE_SIZE = 8


@dataclass(frozen=True)
class GroupHits:
    """Read-only hits of one motion group over a window: ``s``, position in group, normals."""

    window: Window
    s: NDArray[np.float32]
    position: NDArray[np.int32]
    normals: NDArray[np.float32]


class RayGrid:
    """Rays ``origin + s * directions[r, c]`` of one image, plus per-group hit caches.

    Parameters
    ----------
    origin
        (3,) common ray origin (the camera centre), m.
    directions
        ``(H, W, 3)`` float32 ray directions (need not be unit; ``s`` is in their length units).
    project
        ``points (N, 3) -> (uv (N, 2), z (N,))``: pixel coordinates and depth of world points, used
        to bound the pixels a box can cover. With None every ray is used for everything.
    """

    def __init__(
        self, origin: FloatArray, directions: NDArray[np.float32], project: Projector | None = None
    ) -> None:
        self.origin = np.asarray(origin, dtype=np.float64)
        self.directions = directions
        self._project = project
        self._hits: OrderedDict[tuple, GroupHits] = OrderedDict()

    @property
    def shape(self) -> tuple[int, int]:
        return self.directions.shape[0], self.directions.shape[1]

    def window(self, lo: FloatArray, hi: FloatArray) -> Window | None:
        """Pixel window ``(r0, r1, c0, c1)`` an axis-aligned box ``lo``-``hi`` can cover.

        None when the box projects outside the image.
        """
        h, w = self.shape
        if self._project is None:
            return 0, h, 0, w
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        uv, z = self._project(corners)
        if np.any(~(z > 1e-3)):  # the box reaches behind the camera: its projection is unbounded
            return 0, h, 0, w
        # A pixel centre inside the projection lies inside the corners' convex hull, hence the box.
        c0 = max(math.floor(uv[:, 0].min()) - 1, 0)
        c1 = min(math.ceil(uv[:, 0].max()) + 2, w)
        r0 = max(math.floor(uv[:, 1].min()) - 1, 0)
        r1 = min(math.ceil(uv[:, 1].max()) + 2, h)
        if c0 >= c1 or r0 >= r1:
            return None
        return r0, r1, c0, c1

    def cast(
        self,
        scene: o3d.t.geometry.RaycastingScene,
        ids: dict[int, int],
        key: tuple,
        window: Window,
        shift: FloatArray,
        refine: Refiner | None = None,
    ) -> GroupHits:
        """Hits of a group's scene over ``window`` with the rays' origin moved by ``-shift``.

        ``ids`` maps the scene's geometry ids to positions in the group; ``refine``, if given, may
        correct ``s`` and the normals in place before they are cached; results are cached by
        ``(key, window, shift)``.
        """
        cache_key = (key, window, np.asarray(shift, dtype=np.float64).tobytes())
        cached = self._hits.get(cache_key)
        if cached is not None:
            self._hits.move_to_end(cache_key)
            return cached
        r0, r1, c0, c1 = window
        dirs = self.directions[r0:r1, c0:c1]
        rays = np.empty((*dirs.shape[:2], 6), dtype=np.float32)
        rays[..., :3] = (self.origin - shift).astype(np.float32)
        rays[..., 3:] = dirs
        ans = scene.cast_rays(o3d.core.Tensor.from_numpy(rays.reshape(-1, 6)))
        hh, ww = r1 - r0, c1 - c0
        s = ans["t_hit"].numpy().reshape(hh, ww)
        gid = ans["geometry_ids"].numpy().reshape(hh, ww).astype(np.int64)
        lut = np.full(max(ids) + 2, -1, dtype=np.int32)  # the last slot takes the miss id
        for g, position in ids.items():
            lut[g] = position
        position = lut[np.minimum(gid, len(lut) - 1)]
        position[~np.isfinite(s)] = -1
        normals = ans["primitive_normals"].numpy().reshape(hh, ww, 3)
        if refine is not None:
            s, normals = s.copy(), normals.copy()
            refine(self.origin - shift, dirs, s, position, normals)
        for arr in (s, position, normals):
            arr.setflags(write=False)
        hits = self._hits[cache_key] = GroupHits(window, s, position, normals)
        if len(self._hits) > _CACHE_SIZE:
            self._hits.popitem(last=False)
        return hits
