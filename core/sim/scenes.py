"""Ready-made simulated scenes: the perception benchmark set and the two-camera demo layout.

World frame of every scene here: ``x`` forward out of the patient's chest, ``y`` to the patient's
left, ``z`` up, origin on the floor below the seated patient. As in the paper (Sec. III), one
camera (``"front"``) stands in front of the patient and one (``"right45"``) at 45 deg on the
patient's right (the exoskeleton's side), both D435s 0.6-0.9 m from what they watch.

Benchmark scenes hold one body part in front of a wall; each exists without and with an
end-effector occluder (name suffix ``"_occluded"``): a ball at the HIP plus a handle going away
from the body, which hides the closest surface region from a camera looking along the normal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..camera import CameraIntrinsics, look_at
from ..errors import InputError
from ..geometry.primitives import Capsule, Primitive, Sphere
from ..validation import as_finite_scalar, as_unit_vector3, as_vector3
from .bodies import Body, BoxBody, CapsuleBody, CylinderBody, EllipsoidBody, SphereBody
from .depth_camera import SimDepthCamera
from .noise import DepthNoiseConfig
from .world import GroundTruth, SimWorld

FloatArray = NDArray[np.float64]

_UP = np.array([0.0, 0.0, 1.0])


def rotation_xyz(rx_deg: float = 0.0, ry_deg: float = 0.0, rz_deg: float = 0.0) -> FloatArray:
    """Rotation ``Rz @ Ry @ Rx`` from angles in degrees (own frame -> world)."""

    def rot(axis: int, deg: float) -> FloatArray:
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        i, j = [(1, 2), (2, 0), (0, 1)][axis]
        r = np.eye(3)
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        return r

    return rot(2, rz_deg) @ rot(1, ry_deg) @ rot(0, rx_deg)


def paper_cameras(
    target: ArrayLike,
    *,
    distance_m: float = 0.75,
    height_m: float = 0.2,
    intrinsics: CameraIntrinsics | None = None,
    noise: DepthNoiseConfig | None = None,
    decimation: int = 1,
) -> tuple[SimDepthCamera, SimDepthCamera]:
    """The paper's two D435 poses around ``target``: in front and at 45 deg on the patient's right.

    Each camera stands ``distance_m`` from ``target`` horizontally and ``height_m`` above it, and
    looks at it.
    """
    target = as_vector3(target, "target")
    k = intrinsics if intrinsics is not None else CameraIntrinsics.d435()
    cams = []
    for name, yaw_deg in (("front", 0.0), ("right45", -45.0)):
        yaw = math.radians(yaw_deg)
        eye = target + distance_m * np.array([math.cos(yaw), math.sin(yaw), 0.0]) + height_m * _UP
        cams.append(SimDepthCamera(name, k, look_at(eye, target), noise, decimation=decimation))
    return cams[0], cams[1]


def end_effector(
    hip: ArrayLike,
    direction: ArrayLike,
    *,
    ball_radius_m: float = 0.035,
    handle_length_m: float = 0.3,
    handle_radius_m: float = 0.025,
) -> tuple[Sphere, Capsule]:
    """The robot's end effector as occluders: a ball at ``hip`` and a handle along ``direction``."""
    hip = as_vector3(hip, "hip")
    u = as_unit_vector3(direction, "direction")
    return (Sphere(hip, ball_radius_m), Capsule(hip, hip + handle_length_m * u, handle_radius_m))


@dataclass(frozen=True)
class HipSamples:
    """Sampled HIPs ``(N, 3)`` m with the exact ground truth of each."""

    hips: FloatArray
    truths: tuple[GroundTruth, ...]


@dataclass(frozen=True, kw_only=True, eq=False)
class SimScene:
    """A world and the cameras that watch it (``cameras[0]`` in front, ``[1]`` at 45 deg right)."""

    name: str
    world: SimWorld
    cameras: tuple[SimDepthCamera, ...]
    description: str = ""

    def camera(self, name: str) -> SimDepthCamera:
        """The camera called ``name``."""
        for cam in self.cameras:
            if cam.name == name:
                return cam
        have = ", ".join(c.name for c in self.cameras)
        raise InputError(f"camera = {name!r}: no such camera (have {have})")


@dataclass(frozen=True, kw_only=True, eq=False)
class BenchScene(SimScene):
    """A benchmark scene: one ``target`` body, HIP sampler, optional end-effector occluder.

    The end effector's handle leaves the HIP along the surface normal tilted down (like the
    patient's forearm and the robot link under the hand): ``normalize(n - handle_droop * z)``.
    """

    target: str
    with_occluder: bool = False
    handle_droop: float = 0.5
    ee_kwargs: dict = field(default_factory=dict)

    def occluders(self, hip: ArrayLike, t: float = 0.0) -> tuple[Primitive, ...]:
        """The robot primitives for a HIP at ``hip`` (empty without occluder)."""
        if not self.with_occluder:
            return ()
        n = self.world.ground_truth(hip, t).normal
        direction = n - self.handle_droop * _UP
        if np.linalg.norm(direction) < 1e-6:  # normal straight up with droop 1
            direction = n
        return end_effector(hip, direction, **self.ee_kwargs)

    def _hip_for(
        self,
        body: Body,
        p_mesh: FloatArray,
        dist: float,
        cam: SimDepthCamera,
        cos_max: float,
        t: float,
    ) -> tuple[FloatArray | None, GroundTruth | None]:
        sp = body.closest_point(p_mesh, t)
        to_cam = cam.origin_world - sp.point
        if sp.normal @ to_cam < cos_max * np.linalg.norm(to_cam):
            return None, None
        hip = sp.point + dist * sp.normal
        k = cam.intrinsics
        uv, _ = cam.project(np.vstack((sp.point, hip)))
        if not np.all((uv >= 0) & (uv <= [k.width - 1, k.height - 1])):
            return None, None
        truth = self.world.ground_truth(hip, t)
        if truth.body != self.target or abs(truth.distance_m - dist) > 1e-9:
            return None, None
        if any(bg.closest_point(hip, t).distance_m <= dist for bg in self.world.background):
            return None, None
        return hip, truth

    def sample_hips(
        self,
        n: int,
        *,
        seed: int = 0,
        camera: str = "front",
        distance_range_m: tuple[float, float] = (0.04, 0.11),
        max_view_angle_deg: float = 50.0,
        t: float = 0.0,
    ) -> HipSamples:
        """Seeded HIPs near the target, on the side that ``camera`` sees.

        A surface point is drawn uniformly by area (mesh sample projected exactly onto the
        surface), kept if its normal is within ``max_view_angle_deg`` of pointing at the camera
        and it projects into the image; the HIP is that point moved out along the normal by a
        distance uniform in ``distance_range_m``. Every body is convex, so that point is the
        target's closest point; the HIP is kept only if no other patient body is closer and the
        room is farther than the distance too.
        """
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise InputError(f"n = {n!r}: expected a non-negative integer")
        d_lo, d_hi = (as_finite_scalar(v, "distance_range_m") for v in distance_range_m)
        if not 0 < d_lo <= d_hi:
            raise InputError(f"distance_range_m = {distance_range_m}: need 0 < low <= high")
        cos_max = math.cos(math.radians(as_finite_scalar(max_view_angle_deg, "max_view_angle_deg")))
        cam = self.camera(camera)
        body = self.world.body(self.target)
        verts, tris = body.mesh_arrays(t, self.world.mesh_tolerance_m)
        corners = verts[tris]
        area = 0.5 * np.linalg.norm(
            np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
        )
        prob = area / area.sum()
        rng = np.random.default_rng(seed)
        hips: list[FloatArray] = []
        truths: list[GroundTruth] = []
        batch = max(16, 4 * n)
        for _ in range(50):  # batches; each keeps a fair share unless the limits are very tight
            if len(hips) == n:
                break
            tri = corners[rng.choice(len(prob), size=batch, p=prob)]
            ab = rng.random((batch, 2))
            flip = ab.sum(axis=1) > 1
            ab[flip] = 1 - ab[flip]
            edge1, edge2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
            on_mesh = tri[:, 0] + ab[:, :1] * edge1 + ab[:, 1:] * edge2
            dists = rng.uniform(d_lo, d_hi, batch)
            for p_mesh, dist in zip(on_mesh, dists, strict=True):
                if len(hips) == n:
                    break
                hip, truth = self._hip_for(body, p_mesh, float(dist), cam, cos_max, t)
                if hip is not None:
                    hips.append(hip)
                    truths.append(truth)
        if len(hips) < n:
            raise InputError(f"sample_hips: found only {len(hips)} of {n} HIPs; loosen the limits")
        return HipSamples(np.array(hips).reshape(-1, 3), tuple(truths))


def _room(wall_x_m: float, name_prefix: str = "") -> tuple[BoxBody, BoxBody]:
    """A wall behind the patient (its front face at ``x = wall_x_m``) and the floor."""
    wall = BoxBody(
        name=f"{name_prefix}wall",
        part="background",
        center=[wall_x_m - 0.02, 0.0, 1.25],
        half_extents_m=[0.02, 2.5, 1.25],
    )
    floor = BoxBody(
        name=f"{name_prefix}floor",
        part="background",
        center=[0.5, 0.0, -0.02],
        half_extents_m=[2.5, 2.5, 0.02],
    )
    return wall, floor


def _bench(
    name: str,
    body: Body,
    target_point: ArrayLike,
    wall_x_m: float,
    description: str,
    noise: DepthNoiseConfig | None,
    intrinsics: CameraIntrinsics | None,
    decimation: int,
    distance_m: float,
) -> list[BenchScene]:
    world = SimWorld([body], _room(wall_x_m))
    cams = paper_cameras(
        target_point,
        distance_m=distance_m,
        intrinsics=intrinsics,
        noise=noise,
        decimation=decimation,
    )
    return [
        BenchScene(name=name, world=world, cameras=cams, target=body.name, description=description),
        BenchScene(
            name=f"{name}_occluded",
            world=world,
            cameras=cams,
            target=body.name,
            with_occluder=True,
            description=description + "; end effector at the HIP",
        ),
    ]


def perception_bench_scenes(
    noise: DepthNoiseConfig | None = None,
    *,
    intrinsics: CameraIntrinsics | None = None,
    decimation: int = 1,
    camera_distance_m: float = 0.75,
) -> dict[str, BenchScene]:
    """The perception benchmark scenes, each without and with an end-effector occluder.

    ``sphere_head``: a sphere R = 0.09 m; ``ellipsoid_head``: semi-axes 0.095 (front-back),
    0.075 (left-right), 0.115 (up) m, turned 12 deg about z and 8 deg about y;
    ``cylinder_arm``: the left forearm, r = 0.045 m, 0.28 m long, nearly horizontal in front
    of the chest; ``tilted_torso``: a chest plate 0.36 x 0.5 m leaning back 25 deg.
    A wall stands 0.3-0.4 m behind the body. Both paper cameras (``front``, ``right45``) look at
    the body from ``camera_distance_m`` (horizontal) and 0.2 m above.
    """
    head = np.array([0.0, 0.0, 1.25])
    scenes: list[BenchScene] = []
    scenes += _bench(
        "sphere_head",
        SphereBody(name="head", part="skull_forehead", center=head, radius_m=0.09),
        head,
        -0.35,
        "sphere head R 0.09 m",
        noise,
        intrinsics,
        decimation,
        camera_distance_m,
    )
    scenes += _bench(
        "ellipsoid_head",
        EllipsoidBody(
            name="head",
            part="skull_forehead",
            center=head,
            semi_axes_m=[0.095, 0.075, 0.115],
            rotation=rotation_xyz(0.0, 8.0, 12.0),
        ),
        head,
        -0.35,
        "ellipsoid head 0.095 x 0.075 x 0.115 m, rotated",
        noise,
        intrinsics,
        decimation,
        camera_distance_m,
    )
    # Across the chest, so that both cameras see its side (73 and 62 deg off their view axes).
    elbow, wrist = np.array([0.32, 0.25, 0.98]), np.array([0.22, -0.01, 1.02])
    scenes += _bench(
        "cylinder_arm",
        CylinderBody(name="left_forearm", part="forearm", a=elbow, b=wrist, radius_m=0.045),
        0.5 * (elbow + wrist),
        -0.1,
        "left forearm cylinder r 0.045 m",
        noise,
        intrinsics,
        decimation,
        camera_distance_m,
    )
    chest = np.array([0.0, 0.0, 1.0])
    scenes += _bench(
        "tilted_torso",
        BoxBody(
            name="torso",
            part="chest",
            center=chest,
            half_extents_m=[0.03, 0.18, 0.25],
            rotation=rotation_xyz(0, -25, 0),
        ),
        chest,
        -0.4,
        "chest plate leaning back 25 deg",
        noise,
        intrinsics,
        decimation,
        camera_distance_m,
    )
    return {s.name: s for s in scenes}


def demo_scene(
    noise: DepthNoiseConfig | None = None,
    *,
    intrinsics: CameraIntrinsics | None = None,
    decimation: int = 1,
) -> SimScene:
    """The demo layout: a seated patient (head, face, neck, torso, left arm) and both cameras.

    The right arm is in the exoskeleton; the robot itself is passed to each render as occluders.
    """
    R = rotation_xyz
    bodies = [
        EllipsoidBody(
            name="head",
            part="skull_forehead",
            center=[-0.01, 0.0, 1.27],
            semi_axes_m=[0.095, 0.075, 0.11],
            rotation=R(0, 5, 0),
        ),
        EllipsoidBody(
            name="face", part="face", center=[0.05, 0.0, 1.22], semi_axes_m=[0.045, 0.065, 0.075]
        ),
        CapsuleBody(
            name="neck", part="neck", a=[0.0, 0.0, 1.08], b=[0.0, 0.0, 1.17], radius_m=0.05
        ),
        BoxBody(
            name="torso",
            part="chest",
            center=[0.0, 0.0, 0.86],
            half_extents_m=[0.11, 0.18, 0.24],
            rotation=R(0, -8, 0),
        ),
        CapsuleBody(
            name="left_upper_arm",
            part="upper_arm",
            a=[0.0, 0.23, 1.05],
            b=[0.06, 0.26, 0.78],
            radius_m=0.05,
        ),
        CylinderBody(
            name="left_forearm",
            part="forearm",
            a=[0.06, 0.26, 0.78],
            b=[0.32, 0.16, 0.80],
            radius_m=0.042,
        ),
        EllipsoidBody(
            name="left_hand",
            part="hand",
            center=[0.39, 0.13, 0.80],
            semi_axes_m=[0.07, 0.045, 0.02],
            rotation=R(0, 0, -20),
        ),
    ]
    world = SimWorld(bodies, _room(-0.45))
    cams = paper_cameras(
        [0.05, 0.05, 1.02],
        distance_m=0.85,
        height_m=0.35,
        intrinsics=intrinsics,
        noise=noise,
        decimation=decimation,
    )
    return SimScene(
        name="demo",
        world=world,
        cameras=cams,
        description="seated patient: head, face, neck, torso, left arm; two D435s",
    )
