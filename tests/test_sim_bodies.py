"""Simulator bodies: exact closest points, normals, inscribed meshes, motion, world ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hapticloud.core.errors import InputError
from hapticloud.core.sim.bodies import (
    MESH_TOLERANCE_M,
    BoxBody,
    CapsuleBody,
    CylinderBody,
    EllipsoidBody,
    SphereBody,
)
from hapticloud.core.sim.ellipsoid import closest_point_on_ellipsoid
from hapticloud.core.sim.scenes import rotation_xyz
from hapticloud.core.sim.world import SimWorld
from hypothesis import given, settings
from hypothesis import strategies as st

ROT = rotation_xyz(20.0, -35.0, 50.0)
C = np.array([0.1, -0.2, 1.2])


def at(x: float, y: float, z: float) -> np.ndarray:
    """A point offset from ``C``."""
    return C + np.array([x, y, z])


def _fib_sphere(n: int) -> np.ndarray:
    """Near-uniform unit vectors (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.column_stack((r * np.cos(phi), r * np.sin(phi), z))


def _grid(n: int) -> np.ndarray:
    u = (np.arange(n) + 0.5) / n * 2 - 1
    a, b = np.meshgrid(u, u)
    return np.column_stack((a.ravel(), b.ravel()))


def _axis_frame(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    ab = b - a
    length = np.linalg.norm(ab)
    u = ab / length
    e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return u, np.column_stack((e1, np.cross(u, e1))), length


def surface_samples(body) -> np.ndarray:
    """Dense points exactly on the analytic surface (spacing ~1-2 mm), independent of the mesh."""
    if isinstance(body, SphereBody):
        return body.center + body.radius_m * _fib_sphere(40000)
    if isinstance(body, EllipsoidBody):
        return body.center + (_fib_sphere(60000) * body.semi_axes_m) @ body.rotation.T
    if isinstance(body, CapsuleBody):
        u, perp, length = _axis_frame(body.a, body.b)
        dirs = _fib_sphere(20000)
        caps = np.where((dirs @ u)[:, None] < 0, body.a, body.b) + body.radius_m * dirs
        phi = np.linspace(0, 2 * math.pi, 400, endpoint=False)
        h = np.linspace(0, length, 150)
        P, H = np.meshgrid(phi, h)
        ring = np.column_stack((np.cos(P.ravel()), np.sin(P.ravel()))) @ perp.T
        side = body.a + H.ravel()[:, None] * u + body.radius_m * ring
        return np.vstack((caps, side))
    if isinstance(body, CylinderBody):
        u, perp, length = _axis_frame(body.a, body.b)
        phi = np.linspace(0, 2 * math.pi, 400, endpoint=False)
        h = np.linspace(0, length, 150)
        P, H = np.meshgrid(phi, h)
        ring = np.column_stack((np.cos(P.ravel()), np.sin(P.ravel()))) @ perp.T
        side = body.a + H.ravel()[:, None] * u + body.radius_m * ring
        g = _grid(120) * body.radius_m
        g = g[np.linalg.norm(g, axis=1) <= body.radius_m]
        disc = g @ perp.T
        return np.vstack((side, body.a + disc, body.b + disc))
    if isinstance(body, BoxBody):
        faces = []
        g = _grid(120)
        for axis in range(3):
            others = [i for i in range(3) if i != axis]
            for sign in (-1.0, 1.0):
                local = np.zeros((len(g), 3))
                local[:, axis] = sign
                local[:, others] = g
                faces.append(local * body.half_extents_m)
        return body.center + np.vstack(faces) @ body.rotation.T
    raise TypeError(type(body))


BODIES = {
    "sphere": SphereBody(name="s", part="skull_forehead", center=C, radius_m=0.09),
    "ellipsoid": EllipsoidBody(
        name="e", part="skull_forehead", center=C, semi_axes_m=[0.075, 0.095, 0.115], rotation=ROT
    ),
    "capsule": CapsuleBody(name="c", part="upper_arm", a=C, b=at(0.1, 0.2, -0.15), radius_m=0.05),
    "cylinder": CylinderBody(
        name="y", part="forearm", a=C, b=at(0.25, -0.05, 0.03), radius_m=0.045
    ),
    "box": BoxBody(
        name="b", part="chest", center=C, half_extents_m=[0.03, 0.18, 0.25], rotation=ROT
    ),
}


def _queries(body, rng: np.random.Generator, n: int = 30) -> np.ndarray:
    lo, hi = body.bounds()
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    return mid + rng.uniform(-1.6, 1.6, (n, 3)) * half  # outside and inside


@pytest.fixture(scope="module")
def samples() -> dict[str, np.ndarray]:
    return {name: surface_samples(b) for name, b in BODIES.items()}


@pytest.mark.parametrize("name", list(BODIES))
def test_closest_point_beats_dense_brute_force(name: str, samples: dict[str, np.ndarray]) -> None:
    body, pts = BODIES[name], samples[name]
    rng = np.random.default_rng(7)
    for hip in _queries(body, rng):
        point, normal, dist = body.closest_point(hip)
        brute = np.linalg.norm(pts - hip, axis=1)
        # No surface sample is closer than the answer, and the nearest sample is where it says.
        assert abs(dist) <= brute.min() + 1e-12
        assert abs(dist) >= brute.min() - 2.5e-3
        assert np.linalg.norm(pts[np.argmin(brute)] - point) < 0.03
        assert abs(np.linalg.norm(hip - point) - abs(dist)) < 1e-12
        assert abs(body.closest_point(point).distance_m) < 1e-9  # the point is on the surface
        assert abs(np.linalg.norm(normal) - 1) < 1e-12


@pytest.mark.parametrize("name", list(BODIES))
def test_normals_point_outward_along_the_offset(name: str) -> None:
    body = BODIES[name]
    rng = np.random.default_rng(3)
    for hip in _queries(body, rng, 40):
        point, normal, dist = body.closest_point(hip)
        if abs(dist) < 1e-9:
            continue
        # Outside: the HIP lies along +normal; inside: along -normal (smooth parts and edges alike).
        np.testing.assert_allclose((hip - point) / dist, normal, atol=1e-9)
        assert body.closest_point(point + 1e-4 * normal).distance_m > 0


def test_closest_point_simple_values() -> None:
    s = BODIES["sphere"]
    sp = s.closest_point(at(0.2, 0, 0))
    np.testing.assert_allclose(sp.point, at(0.09, 0, 0), atol=1e-15)
    assert sp.distance_m == pytest.approx(0.11)
    assert s.closest_point(C).distance_m == pytest.approx(-0.09)
    box = BoxBody(name="b", part="chest", center=[0, 0, 0], half_extents_m=[0.1, 0.2, 0.3])
    assert box.closest_point([0.0, 0.0, 0.05]).distance_m == pytest.approx(-0.1)
    assert box.closest_point([0.3, 0.5, 0.0]).distance_m == pytest.approx(math.hypot(0.2, 0.3))
    cyl = CylinderBody(name="y", part="forearm", a=[0, 0, 0], b=[0, 0, 0.4], radius_m=0.05)
    sp = cyl.closest_point([0.1, 0.0, 0.5])  # beyond the rim
    np.testing.assert_allclose(sp.point, [0.05, 0, 0.4], atol=1e-15)
    assert sp.distance_m == pytest.approx(math.hypot(0.05, 0.1))
    assert cyl.closest_point([0.0, 0.0, 0.39]).distance_m == pytest.approx(-0.01)  # near a cap
    cap = CapsuleBody(name="c", part="upper_arm", a=[0, 0, 0], b=[0, 0, 0.3], radius_m=0.05)
    sp = cap.closest_point([0.0, 0.0, 0.1])  # on the axis: some radial direction
    assert sp.distance_m == pytest.approx(-0.05)
    assert abs(sp.normal[2]) < 1e-12


# ----- ellipsoid: Eberly's method at its degenerate spots ---------------------------------------

E = np.array([0.075, 0.095, 0.115])


def _kkt_residual(e: np.ndarray, q: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """(|on-surface residual|, |component of q - x across the normal|)."""
    on_surface = abs(float(np.sum((x / e) ** 2) - 1.0))
    n = x / e**2
    n /= np.linalg.norm(n)
    offset = q - x
    return on_surface, float(np.linalg.norm(offset - (offset @ n) * n))


@pytest.mark.parametrize(
    ("q", "expected"),
    [
        ([0.0, 0.0, 0.0], 0.075),  # centre: the end of the smallest axis
        ([0.0, 0.0, 0.05], 0.075 - 0.0),  # major axis, near the centre: off-axis, still 0.075-ish
        ([0.0, 0.0, 0.3], 0.3 - 0.115),  # outside on the major axis
        ([0.2, 0.0, 0.0], 0.2 - 0.075),  # outside on the minor axis
        ([0.0, 0.05, 0.0], 0.095 - 0.05),  # middle axis, inside
        ([0.03, 0.0, 0.0], 0.075 - 0.03),  # minor axis, inside
        ([0.075, 0.0, 0.0], 0.0),  # on the surface
    ],
)
def test_ellipsoid_degenerate_queries(q: list[float], expected: float) -> None:
    q = np.array(q)
    x = closest_point_on_ellipsoid(E, q)
    on_surface, across = _kkt_residual(E, q, x)
    assert on_surface < 1e-12 and across < 1e-12
    brute = np.linalg.norm(_fib_sphere(200000) * E - q, axis=1).min()
    dist = np.linalg.norm(q - x)
    assert dist <= brute + 1e-12
    if q[2] == 0.0 or q[0] != 0.0 or q[1] != 0.0 or abs(q[2]) >= 0.115:
        assert dist == pytest.approx(expected, abs=1e-12)
    else:  # inside on the major axis: the closed form of the off-axis point
        xde = E[2] * q[2] / (E[2] ** 2 - E[0] ** 2)
        assert dist == pytest.approx(math.hypot(E[2] * xde - q[2], E[0] * math.sqrt(1 - xde**2)))


def test_ellipsoid_centre_of_body_world_frame() -> None:
    body = BODIES["ellipsoid"]
    _, normal, dist = body.closest_point(C)
    assert dist == pytest.approx(-0.075, abs=1e-12)
    minor_axis = ROT[:, 0]
    assert abs(abs(normal @ minor_axis) - 1) < 1e-12


@settings(max_examples=150, deadline=None)
@given(
    axes=st.lists(st.floats(0.01, 0.3), min_size=3, max_size=3),
    direction=st.lists(st.floats(-1, 1), min_size=3, max_size=3),
    scale=st.one_of(st.floats(0.0, 3.0), st.floats(1 - 1e-9, 1 + 1e-9), st.floats(3.0, 1e3)),
    snap=st.sampled_from(["none", "axis0", "axis1", "axis2", "plane01", "equal"]),
)
def test_ellipsoid_property_kkt_and_global(axes, direction, scale, snap) -> None:
    e = np.array(axes)
    if snap == "equal":
        e[1] = e[0]
    q = np.array(direction) * scale * e
    if snap.startswith("axis"):
        keep = int(snap[-1])
        q = np.where(np.arange(3) == keep, q, 0.0)
    elif snap == "plane01":
        q[2] = 0.0
    x = closest_point_on_ellipsoid(e, q)
    on_surface, across = _kkt_residual(e, q, x)
    assert on_surface < 1e-12
    assert across < 1e-15 + 1e-10 * float(np.linalg.norm(q - x))  # offset along the normal
    brute = np.linalg.norm(_fib_sphere(20000) * e - q, axis=1).min()
    assert np.linalg.norm(q - x) <= brute + 1e-12


# ----- meshes ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(BODIES))
def test_mesh_is_inscribed_within_tolerance_and_outward(name: str) -> None:
    body = BODIES[name]
    v, f = body.mesh_arrays()
    rng = np.random.default_rng(0)
    some_v = v[rng.choice(len(v), min(len(v), 300), replace=False)]
    assert max(abs(body.closest_point(p).distance_m) for p in some_v) < 1e-9
    tri = v[f[rng.choice(len(f), min(len(f), 300), replace=False)]]
    for bary in ([1 / 3, 1 / 3, 1 / 3], [0.5, 0.5, 0.0], [0.0, 0.5, 0.5]):
        pts = np.einsum("k,nkd->nd", np.array(bary), tri)
        d = np.array([body.closest_point(p).distance_m for p in pts])
        assert d.max() < 1e-9  # inside or on: the mesh is inscribed
        assert d.min() > -MESH_TOLERANCE_M * 1.01
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centroid = tri.mean(axis=1)
    outward = np.array([body.closest_point(c).normal for c in centroid])
    assert np.all(np.einsum("ij,ij->i", normals, outward) > 0)


def test_open3d_mesh_and_tolerance_scaling() -> None:
    body = BODIES["sphere"]
    mesh = body.mesh()
    assert len(mesh.triangles) == len(body.mesh_arrays()[1])
    for other in BODIES.values():  # closed surfaces (coarse meshes: the check is slow)
        coarse_mesh = other.mesh(tolerance_m=1e-3)
        assert coarse_mesh.is_watertight() and coarse_mesh.is_orientable()
    coarse = body.mesh_arrays(tolerance_m=1e-4)[1]
    assert len(coarse) < len(body.mesh_arrays()[1]) / 5


# ----- rays ------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(BODIES))
def test_analytic_rays_hit_the_surface(name: str) -> None:
    body = BODIES[name]
    rng = np.random.default_rng(5)
    origin = C + np.array([0.8, 0.3, 0.2])
    lo, hi = body.bounds()
    targets = rng.uniform(lo, hi, (500, 3))
    t, n = body.intersect_rays(origin, targets - origin)
    hit = np.isfinite(t)
    assert hit.sum() > 50
    pts = origin + t[hit, None] * (targets[hit] - origin)
    d = np.array([body.closest_point(p).distance_m for p in pts])
    assert np.abs(d).max() < 1e-9
    assert np.all(np.einsum("ij,ij->i", n[hit], targets[hit] - origin) < 0)  # front faces
    inside = np.array([body.closest_point(p).distance_m < 0 for p in targets])
    assert np.all(hit[inside])  # a ray to a point inside must hit


# ----- motion, world, validation ---------------------------------------------------------------


def test_velocity_and_moved_translate_everything() -> None:
    body = SphereBody(
        name="s", part="skull_forehead", center=C, radius_m=0.09, velocity_mps=[0.0, 0.5, 0.0]
    )
    hip = at(0.2, 0.5, 0.0)
    sp = body.closest_point(hip, t=1.0)
    np.testing.assert_allclose(sp.point, at(0.09, 0.5, 0.0), atol=1e-15)
    moved = body.moved([0.0, 0.0, 0.1])
    np.testing.assert_allclose(moved.closest_point(at(0.2, 0, 0.1)).point, at(0.09, 0, 0.1))
    assert moved.shape_key() == body.shape_key()  # the rest mesh is shared
    v0, _ = body.mesh_arrays(t=0.0)
    v1, _ = moved.mesh_arrays(t=2.0)
    np.testing.assert_allclose(v1 - v0, np.tile([0.0, 1.0, 0.1], (len(v0), 1)), atol=1e-12)
    assert body.bounds(t=1.0)[0][1] == pytest.approx(C[1] + 0.5 - 0.09)


def test_world_ground_truth_picks_the_nearest_patient_body_not_the_background() -> None:
    head = SphereBody(name="head", part="skull_forehead", center=[0, 0, 1.25], radius_m=0.09)
    torso = BoxBody(
        name="torso", part="chest", center=[0, 0, 0.9], half_extents_m=[0.1, 0.18, 0.22]
    )
    wall = BoxBody(
        name="wall", part="background", center=[0.3, 0, 1.2], half_extents_m=[0.01, 1, 1]
    )
    world = SimWorld([head, torso], [wall])
    gt = world.ground_truth([0.2, 0.0, 1.25])  # the wall (0.09 away) is nearer than the head
    assert (gt.body, gt.part) == ("head", "skull_forehead")
    assert gt.distance_m == pytest.approx(0.11)
    gt = world.ground_truth([0.15, 0.0, 1.0])
    assert gt.body == "torso" and gt.distance_m == pytest.approx(0.05)
    moved = world.moved("head", [0.0, 0.0, 0.1])
    assert moved.ground_truth([0.2, 0.0, 1.35]).distance_m == pytest.approx(0.11)
    assert world.body("head").center[2] == 1.25  # the original world is untouched


def test_bad_arguments_name_the_argument() -> None:
    with pytest.raises(InputError, match="part"):
        SphereBody(name="s", part="elbow", center=C, radius_m=0.1)
    with pytest.raises(InputError, match="radius_m"):
        SphereBody(name="s", part="face", center=C, radius_m=-0.1)
    with pytest.raises(InputError, match="semi_axes_m"):
        EllipsoidBody(name="e", part="face", center=C, semi_axes_m=[0.1, 0.0, 0.1])
    with pytest.raises(InputError, match="rotation"):
        BoxBody(
            name="b", part="chest", center=C, half_extents_m=[1, 1, 1], rotation=np.ones((3, 3))
        )
    with pytest.raises(InputError, match="b: must differ"):
        CylinderBody(name="y", part="forearm", a=C, b=C, radius_m=0.05)
    with pytest.raises(InputError, match="hip"):
        BODIES["sphere"].closest_point([0.0, np.nan, 0.0])
    with pytest.raises(InputError, match="unique"):
        SimWorld([BODIES["sphere"], BODIES["sphere"]])
    with pytest.raises(InputError, match="no such body"):
        SimWorld([BODIES["sphere"]]).body("nobody")
