"""One camera's bundle of pixel rays, with the caches that make per-frame ray casting cheap.

Casting all 407k rays of an 848x480 image costs ~14 ms on 2 cores (~28 ms on one), most of a
frame's budget, although the room and a still patient look the same in every frame. A
:class:`RayGrid` therefore keeps, per motion group of the world, the last hits keyed by the
group's shapes and its displacement: a static group is cast once per camera, a moving one only
over the image window its bounding box covers.

A render may also ask for a *part* of the image only (a region of interest, e.g. the pixels the
perception's crop will look at). A moving group is then cast over that part alone; a group that
has not moved since its last cast is cast over its whole window once and later parts are sliced
from that (the room does not move, the region of interest does). Every ray's hit is independent
of the other rays cast with it, so a part is bit for bit the same as the whole there.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
Window = tuple[int, int, int, int]
Projector = Callable[[FloatArray], tuple[FloatArray, FloatArray]]
#: ``(origin_rest, directions, s, position, normals) -> None``: corrects hits in place.
Refiner = Callable[
    [FloatArray, NDArray[np.float32], NDArray[np.float32], NDArray[np.int32], NDArray[np.float32]],
    None,
]

_CACHE_SIZE = 8


def intersect_windows(a: Window, b: Window) -> Window | None:
    """The overlap of two half-open pixel windows ``(r0, r1, c0, c1)``, None when empty."""
    r0, r1 = max(a[0], b[0]), min(a[1], b[1])
    c0, c1 = max(a[2], b[2]), min(a[3], b[3])
    if r0 >= r1 or c0 >= c1:
        return None
    return r0, r1, c0, c1


def _contains(outer: Window, inner: Window) -> bool:
    return (
        outer[0] <= inner[0]
        and inner[1] <= outer[1]
        and outer[2] <= inner[2]
        and inner[3] <= outer[3]
    )


@dataclass(frozen=True)
class GroupHits:
    """Read-only hits of one motion group over a window: ``s``, position in group, normals."""

    window: Window
    s: NDArray[np.float32]
    position: NDArray[np.int32]
    normals: NDArray[np.float32]

    def part(self, window: Window) -> GroupHits:
        """Read-only views of the hits over ``window``, which must lie inside :attr:`window`."""
        r0, c0 = window[0] - self.window[0], window[2] - self.window[2]
        rows = slice(r0, r0 + window[1] - window[0])
        cols = slice(c0, c0 + window[3] - window[2])
        return GroupHits(
            window, self.s[rows, cols], self.position[rows, cols], self.normals[rows, cols]
        )


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
        # Per group key, the shift of its last cast: a group seen again at the same shift is
        # static, so its whole window is worth casting once and slicing from afterwards.
        self._last_shift: dict[tuple, bytes] = {}
        self._planes: tuple[tuple[FloatArray, FloatArray, FloatArray], FloatArray] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.directions.shape[0], self.directions.shape[1]

    def window(self, lo: FloatArray, hi: FloatArray) -> Window | None:
        """Pixel window ``(r0, r1, c0, c1)`` an axis-aligned box ``lo``-``hi`` can cover.

        None when the box projects outside the image.
        """
        return self.windows(np.reshape(lo, (1, 3)), np.reshape(hi, (1, 3)))[0]

    def windows(self, lows: ArrayLike, highs: ArrayLike) -> list[Window | None]:
        """:meth:`window` of ``N`` boxes ``(N, 3)`` at once (one projection for all corners)."""
        lo = np.asarray(lows, dtype=np.float64).reshape(-1, 3)
        hi = np.asarray(highs, dtype=np.float64).reshape(-1, 3)
        h, w = self.shape
        if self._project is None:
            return [(0, h, 0, w)] * lo.shape[0]
        # The 8 corners of each box: corner k takes hi on axis j when bit j of k is set.
        bits = ((np.arange(8)[:, None] >> np.arange(3)) & 1).astype(bool)
        corners = np.where(bits[None], hi[:, None, :], lo[:, None, :])
        uv, z = self._project(corners.reshape(-1, 3))
        uv, z = uv.reshape(-1, 8, 2), z.reshape(-1, 8)
        out: list[Window | None] = []
        for box_uv, box_z in zip(uv, z, strict=True):
            if np.any(~(box_z > 1e-3)):  # the box reaches behind the camera: unbounded projection
                out.append((0, h, 0, w))
                continue
            # A pixel centre inside the projection lies inside the corners' convex hull, hence
            # the box.
            c0 = max(math.floor(box_uv[:, 0].min()) - 1, 0)
            c1 = min(math.ceil(box_uv[:, 0].max()) + 2, w)
            r0 = max(math.floor(box_uv[:, 1].min()) - 1, 0)
            r1 = min(math.ceil(box_uv[:, 1].max()) + 2, h)
            out.append(None if c0 >= c1 or r0 >= r1 else (r0, r1, c0, c1))
        return out

    def planes(self) -> tuple[tuple[FloatArray, FloatArray, FloatArray], FloatArray]:
        """The directions as three float64 ``(H, W)`` coordinate planes and their squared
        lengths, cached: closed-form occluder tests slice windows of them without a gather."""
        if self._planes is None:
            d = self.directions.astype(np.float64)
            planes = (
                np.ascontiguousarray(d[..., 0]),
                np.ascontiguousarray(d[..., 1]),
                np.ascontiguousarray(d[..., 2]),
            )
            dd = planes[0] * planes[0] + planes[1] * planes[1] + planes[2] * planes[2]
            for arr in (*planes, dd):
                arr.setflags(write=False)
            self._planes = (planes, dd)
        return self._planes

    def cast(
        self,
        scene: o3d.t.geometry.RaycastingScene,
        ids: dict[int, int],
        key: tuple,
        window: Window,
        shift: FloatArray,
        refine: Refiner | None = None,
        part: Window | None = None,
    ) -> GroupHits:
        """Hits of a group's scene over ``window`` with the rays' origin moved by ``-shift``.

        ``ids`` maps the scene's geometry ids to positions in the group; ``refine``, if given, may
        correct ``s`` and the normals in place before they are cached; results are cached by
        ``(key, window, shift)``. ``part`` (inside ``window``): only these pixels are needed;
        the hits returned cover ``part`` and are the same as the whole window's there.
        """
        shift_key = np.asarray(shift, dtype=np.float64).tobytes()
        whole = self._cached((key, window, shift_key))
        if part is None or part == window:
            if whole is None:
                whole = self._cast(scene, ids, (key, window, shift_key), window, shift, refine)
            self._last_shift[key] = shift_key
            return whole
        if whole is not None:
            return whole.part(part)
        if self._last_shift.get(key) == shift_key:
            # Not moved since its last cast: cast the whole window once, slice from it after.
            whole = self._cast(scene, ids, (key, window, shift_key), window, shift, refine)
            return whole.part(part)
        self._last_shift[key] = shift_key
        for (k, w, sk), hits in self._hits.items():
            if k == key and sk == shift_key and _contains(w, part):
                return hits.part(part)
        return self._cast(scene, ids, (key, part, shift_key), part, shift, refine)

    def _cached(self, cache_key: tuple) -> GroupHits | None:
        cached = self._hits.get(cache_key)
        if cached is not None:
            self._hits.move_to_end(cache_key)
        return cached

    def _cast(
        self,
        scene: o3d.t.geometry.RaycastingScene,
        ids: dict[int, int],
        cache_key: tuple,
        window: Window,
        shift: FloatArray,
        refine: Refiner | None,
    ) -> GroupHits:
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
