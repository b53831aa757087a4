"""Simulator bodies: exact closest points, normals, inscribed meshes, motion, world ground truth."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import open3d as o3d
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
from hypothesis import example, given, settings
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
# Found by hypothesis: a subnormal query put the bisection's parameter in the subnormals.
@example(axes=[0.25, 0.25, 0.25], direction=[0.0, 1.0, 1.0], scale=2.2250738585e-313, snap="none")
@example(axes=[0.1, 0.1, 0.1], direction=[1e-310, 2e-310, 3e-310], scale=1.0, snap="none")
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


# ----- closest points anywhere: on an axis, at the centre, far from the origin ------------------
#
# The checks below never ask the body about its own answer: each shape's signed distance is
# computed here in closed form (the ellipsoid, which has none, by its implicit function and by
# dense sampling of its surface), and Open3D's distance to a fine mesh checks it once more.

FAR = np.array([1e3, -1e3, 1e3])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _perp(u: np.ndarray) -> np.ndarray:
    return _unit(np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0]))


def _scale(*arrays: np.ndarray) -> float:
    """Magnitude of the coordinates involved (m): the rounding errors scale with it."""
    return 1.0 + max(float(np.abs(a).max()) for a in arrays)


def _tol(*arrays: np.ndarray) -> float:
    """Round-off allowed on a distance or a coordinate (m): ~100 ulps of the coordinates."""
    return 2e-14 * _scale(*arrays)


def reference_sdf(body, x: np.ndarray, t: float = 0.0) -> float | None:
    """Signed distance from ``x`` (world) to the body at time ``t`` in closed form (None for the
    ellipsoid: no closed form)."""
    x = np.asarray(x, dtype=np.float64) - body.displacement(t)
    if isinstance(body, SphereBody):
        return float(np.linalg.norm(x - body.center) - body.radius_m)
    if isinstance(body, CapsuleBody):
        ab = body.b - body.a
        s = float(np.clip((x - body.a) @ ab / (ab @ ab), 0.0, 1.0))
        return float(np.linalg.norm(x - (body.a + s * ab)) - body.radius_m)
    if isinstance(body, CylinderBody):
        ab = body.b - body.a
        u = _unit(ab)
        rel = x - 0.5 * (body.a + body.b)
        h = float(rel @ u)
        rho = float(np.linalg.norm(rel - h * u))
        d = np.array([rho - body.radius_m, abs(h) - 0.5 * np.linalg.norm(ab)])
        return float(min(d.max(), 0.0) + np.linalg.norm(np.maximum(d, 0.0)))
    if isinstance(body, BoxBody):
        d = np.abs((x - body.center) @ body.rotation) - body.half_extents_m
        return float(min(d.max(), 0.0) + np.linalg.norm(np.maximum(d, 0.0)))
    return None


def _ellipsoid_level(body: EllipsoidBody, x: np.ndarray) -> float:
    """Implicit function of the ellipsoid, ``sum (x_i / a_i)^2 - 1`` (own frame)."""
    local = ((x - body.displacement()) - body.center) @ body.rotation
    return float(np.sum((local / body.semi_axes_m) ** 2) - 1.0)


def check_closest_point(body, hip: np.ndarray) -> None:
    """The answer for ``hip`` is a surface point, a unit normal and the signed distance."""
    point, normal, dist = body.closest_point(hip)
    lo, hi = body.bounds()
    tol = _tol(hip, lo, hi)
    assert abs(np.linalg.norm(normal) - 1.0) < 1e-12, normal
    assert abs(np.linalg.norm(hip - point) - abs(dist)) <= tol, (dist, point)
    ref_at_point, ref_at_hip = reference_sdf(body, point), reference_sdf(body, hip)
    if ref_at_point is not None:
        assert abs(ref_at_point) <= tol, f"closest point {ref_at_point:.3g} m off the surface"
        assert abs(ref_at_hip - dist) <= tol, (ref_at_hip, dist)  # the distance, and its sign
    else:  # ellipsoid: on the level set, on the right side, no surface sample nearer
        e_min = float(body.semi_axes_m.min())
        assert abs(_ellipsoid_level(body, point)) * e_min <= 4 * tol
        level = _ellipsoid_level(body, hip)
        if abs(level) * e_min > 4 * tol:
            assert (dist < 0) == (level < 0)
        samples = (
            body.displacement()
            + body.center
            + (_fib_sphere(20000) * body.semi_axes_m) @ body.rotation.T
        )
        assert abs(dist) <= np.linalg.norm(samples - hip, axis=1).min() + tol
    if abs(dist) > 1e-6:  # off the surface: the HIP lies along the normal from the point
        np.testing.assert_allclose((hip - point) / dist, normal, atol=1e-6)


@pytest.mark.parametrize("far", [0.0, 1e3])
@pytest.mark.parametrize("name", ["capsule", "cylinder"])
def test_a_query_on_the_axis_gets_a_surface_point_and_a_radial_normal(name, far) -> None:
    base = BODIES[name]
    shift = far * np.array([1.0, -1.0, 1.0])
    # Far from the origin both ways: the rest shape out there, or a body moved out there.
    for body in (base.moved(shift), dataclasses.replace(base, a=base.a + shift, b=base.b + shift)):
        a, b = body.a + body.offset_m, body.b + body.offset_m
        u, length = _unit(b - a), float(np.linalg.norm(b - a))
        # The side is nearest all along a capsule; a cylinder's caps within a radius of them.
        cap = 0.0 if name == "capsule" else body.radius_m / length
        for s in np.concatenate((np.linspace(-0.3, 1.3, 321), [0.0, 0.5, 1.0])):
            hip = a + s * (b - a)  # on the axis within rounding
            check_closest_point(body, hip)
            _, normal, dist = body.closest_point(hip)
            if cap + 1e-9 < s < 1 - cap - 1e-9:  # a radial normal, the radius deep
                assert abs(normal @ u) < 1e-12
                assert dist == pytest.approx(-body.radius_m, abs=_tol(hip))
        check_closest_point(body, a)
        check_closest_point(body, b)
        check_closest_point(body, 0.5 * (a + b))


@pytest.mark.parametrize("far", [0.0, 1e3])
def test_cylinder_rim_normal_is_unit_and_points_from_the_rim_circle(far) -> None:
    base = BODIES["cylinder"]
    shift = far * np.array([1.0, -1.0, 1.0])
    body = dataclasses.replace(base, a=base.a + shift, b=base.b + shift)
    u = _unit(body.b - body.a)
    e1 = _perp(u)
    e2 = np.cross(u, e1)
    steps = [0.0, 5e-324, 1e-300, 1e-16, 1e-13, 1e-10, 1e-6, 1e-3, 0.05]
    rng = np.random.default_rng(11)
    for end, side in ((body.a, -1.0), (body.b, 1.0)):
        for phi in np.linspace(0.0, 2 * math.pi, 7, endpoint=False):
            radial = math.cos(phi) * e1 + math.sin(phi) * e2
            rim = end + body.radius_m * radial
            for dr in steps:
                for dh in steps:
                    hip = rim + dr * radial + dh * side * u
                    check_closest_point(body, hip)
                    if dr >= 1e-6 and dh >= 1e-6:  # beyond the edge: the rim point, from it
                        point, normal, dist = body.closest_point(hip)
                        np.testing.assert_allclose(point, rim, atol=_tol(hip))
                        # hip - rim here is only as exact as the coordinates' round-off
                        along = _tol(hip) / math.hypot(dr, dh)
                        np.testing.assert_allclose(normal, _unit(hip - rim), atol=1e-12 + along)
                        assert dist == pytest.approx(math.hypot(dr, dh), abs=_tol(hip))
            for _ in range(20):  # within rounding of the rim, any way
                check_closest_point(body, rim + rng.normal(size=3) * 10 ** rng.uniform(-17, -9))


# Exact directions (an axis of the body's frame), and ones with subnormal or tiny components.
_COMPONENT = st.one_of(
    st.floats(-1.0, 1.0),
    st.sampled_from([0.0, 5e-324, -5e-324, 2.2250738585e-313, -1e-310, 1e-300, 1e-17, -1e-16]),
)
_DIRECTION = st.lists(_COMPONENT, min_size=3, max_size=3)


@st.composite
def body_and_query(draw) -> tuple[object, np.ndarray]:
    """Any body type, at the origin or 1e3 m out (as its rest shape or moved there), and a
    query anywhere, on one of its axes, at its centre, near its surface or a subnormal step off
    its centre."""
    kind = draw(st.sampled_from(["sphere", "ellipsoid", "capsule", "cylinder", "box"]))
    centre = np.array(draw(st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3)))
    far = draw(st.sampled_from(["origin", "rest_far", "moved_far"]))
    if far == "rest_far":
        centre = centre + FAR
    angles = draw(st.one_of(st.just((0.0, 0.0, 0.0)), st.tuples(*[st.floats(-180.0, 180.0)] * 3)))
    rot = rotation_xyz(*angles)
    size = st.floats(0.01, 0.3)
    if kind == "sphere":
        body = SphereBody(name="q", part="face", center=centre, radius_m=draw(size))
        frame, reach = np.eye(3), np.full(3, body.radius_m)
    elif kind == "ellipsoid":
        axes = np.array(draw(st.lists(size, min_size=3, max_size=3)))
        body = EllipsoidBody(name="q", part="face", center=centre, semi_axes_m=axes, rotation=rot)
        frame, reach = rot, axes
    elif kind == "box":
        half = np.array(draw(st.lists(size, min_size=3, max_size=3)))
        body = BoxBody(name="q", part="chest", center=centre, half_extents_m=half, rotation=rot)
        frame, reach = rot, half
    else:
        length, radius = draw(st.floats(0.02, 0.6)), draw(size)
        half_axis = 0.5 * length * rot[:, 2]
        cls = CapsuleBody if kind == "capsule" else CylinderBody
        body = cls(
            name="q", part="forearm", a=centre - half_axis, b=centre + half_axis, radius_m=radius
        )
        frame = np.column_stack((rot[:, 0], rot[:, 1], rot[:, 2]))
        reach = np.array([radius, radius, 0.5 * length + (radius if kind == "capsule" else 0)])
    if far == "moved_far":
        body = body.moved(FAR)
        centre = centre + FAR
    where = draw(st.sampled_from(["anywhere", "axis", "centre", "surface", "subnormal"]))
    if where == "anywhere":
        u = np.array(draw(st.lists(st.floats(-1.6, 1.6), min_size=3, max_size=3)))
        lo, hi = body.bounds()
        hip = 0.5 * (lo + hi) + u * 0.5 * (hi - lo)
    elif where == "axis":
        k = draw(st.integers(0, 2))
        hip = centre + draw(st.floats(-1.6, 1.6)) * reach[k] * frame[:, k]
    elif where == "centre":
        hip = centre.copy()
    elif where == "surface":
        point = body.closest_point(centre + np.array(draw(_DIRECTION)) * 10.0).point
        hip = point + np.array(draw(_DIRECTION)) * draw(st.sampled_from([1e-15, 1e-9, 1e-3]))
    else:
        hip = centre + np.array(draw(_DIRECTION)) * draw(st.sampled_from([1.0, 1e-300, 1e-310]))
    return body, hip


@settings(max_examples=300, deadline=None)
@given(case=body_and_query())
def test_property_closest_point_is_on_the_surface_with_a_unit_normal_and_signed_distance(
    case,
) -> None:
    body, hip = case
    check_closest_point(body, hip)


@pytest.mark.parametrize("name", list(BODIES))
def test_closest_point_agrees_with_open3d_on_a_fine_mesh(name: str) -> None:
    body = BODIES[name]
    v, f = body.mesh_arrays()  # inscribed within MESH_TOLERANCE_M
    scene = o3d.t.geometry.RaycastingScene()
    # Open3D works in float32: the mesh is built about the body's centre, and so are the queries.
    lo, hi = body.bounds()
    mid = 0.5 * (lo + hi)
    scene.add_triangles(
        o3d.core.Tensor((v - mid).astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32))
    )
    rng = np.random.default_rng(17)
    queries = [*_queries(body, rng, 200), mid]
    if isinstance(body, (CapsuleBody, CylinderBody)):
        queries += [body.a + s * (body.b - body.a) for s in np.linspace(-0.2, 1.2, 57)]
    elif isinstance(body, (EllipsoidBody, BoxBody)):
        reach = body.semi_axes_m if isinstance(body, EllipsoidBody) else body.half_extents_m
        queries += [
            body.center + s * reach[k] * body.rotation[:, k]
            for k in range(3)
            for s in np.linspace(-1.4, 1.4, 29)
        ]
    queries = np.array(queries)
    ref = scene.compute_signed_distance(o3d.core.Tensor((queries - mid).astype(np.float32))).numpy()
    for far in (np.zeros(3), FAR):  # the same answers 1e3 m away, to round-off
        moved = body.moved(far)
        got = np.array([moved.closest_point(q + far).distance_m for q in queries])
        # The inscribed mesh lies within MESH_TOLERANCE_M inside the surface; float32 adds ~1e-7.
        np.testing.assert_allclose(got, ref, atol=MESH_TOLERANCE_M * 1.01 + 2e-7)
        for q in queries:
            check_closest_point(moved, q + far)


@pytest.mark.parametrize(
    ("axes", "q"),
    [
        ([0.25, 0.25, 0.25], [0.0, 0.25 * 2.2250738585e-313, 0.25 * 2.2250738585e-313]),
        ([0.1, 0.1, 0.1], [1e-311, 2e-311, 3e-311]),
        ([0.2, 0.2, 0.3], [2e-311, 2e-311, 0.075]),
        ([0.2, 0.2, 0.3], [2e-311, 2e-311, 0.0]),
        ([0.2, 0.1, 0.1], [2e-311, 2e-311, 3e-311]),
        ([0.2, 0.1, 0.3], [5e-324, 0.05, 0.075]),
        ([0.3, 0.2, 0.1], [5e-324, 5e-324, 5e-324]),
    ],
)
def test_ellipsoid_queries_with_subnormal_components(axes, q) -> None:
    """Queries a subnormal step from a symmetry plane or the centre: the closest point is on
    the surface to the last bits (the bisection's parameter used to be subnormal itself)."""
    e, q = np.array(axes), np.array(q)
    x = closest_point_on_ellipsoid(e, q)
    on_surface, across = _kkt_residual(e, q, x)
    assert on_surface < 1e-15 and across < 1e-15
    brute = np.linalg.norm(_fib_sphere(20000) * e - q, axis=1).min()
    assert np.linalg.norm(q - x) <= brute + 1e-12


@pytest.mark.parametrize("name", list(BODIES))
def test_distance_lower_bound_never_exceeds_the_signed_distance(name: str, samples) -> None:
    body = BODIES[name].moved([0.01, -0.02, 0.03])
    shift = np.array([0.01, -0.02, 0.03])
    surface = samples[name] + shift
    rng = np.random.default_rng(11)
    for q in _queries(body, rng, 60):
        low = body.distance_lower_bound(q)
        exact = body.closest_point(q).distance_m
        assert low <= exact + 1e-12
        # The box holds every surface point: no sample is nearer than the bound either.
        assert low <= float(np.min(np.linalg.norm(surface - q, axis=1))) + 1e-12
    lo, hi = body.bounds()
    assert body.distance_lower_bound(0.5 * (lo + hi)) == -math.inf  # inside the box


def test_ground_truth_skipping_far_boxes_equals_every_body_in_order(monkeypatch) -> None:
    # Spread out and moving: most boxes lie beyond the nearest body's distance and are skipped.
    bodies = [
        dataclasses.replace(b.moved([0.3 * i, 0.0, 0.0]), velocity_mps=np.array([0.0, 0.05 * i, 0]))
        for i, b in enumerate(BODIES.values())
    ]
    world = SimWorld(bodies)
    rng = np.random.default_rng(12)
    lo = np.min([b.bounds()[0] for b in bodies], axis=0) - 0.1
    hi = np.max([b.bounds()[1] for b in bodies], axis=0) + 0.1
    calls: list[int] = []
    skipped: list[int] = []
    for kind in {type(b) for b in bodies}:
        exact = kind.closest_point
        monkeypatch.setattr(
            kind,
            "closest_point",
            lambda self, *a, _f=exact, **k: calls.append(1) or _f(self, *a, **k),
        )
    for q, t in zip(rng.uniform(lo, hi, (300, 3)), rng.uniform(0.0, 2.0, 300), strict=True):
        calls.clear()
        truth = world.ground_truth(q, t)
        asked = len(calls)
        brute = min(
            ((b.closest_point(q, t), i) for i, b in enumerate(bodies)),
            key=lambda item: (item[0].distance_m, item[1]),
        )
        skipped.append(len(bodies) - asked)
        assert truth.body == bodies[brute[1]].name
        assert truth.distance_m == brute[0].distance_m
        assert np.array_equal(truth.point, brute[0].point)
    assert sum(skipped) > 2 * len(skipped)  # the bound does skip bodies, most of the time


@pytest.mark.parametrize("kind", [CapsuleBody, CylinderBody])
def test_a_query_a_subnormal_distance_off_the_axis_gets_a_unit_normal(kind) -> None:
    """Found by the property test above: an axis 1.6e-160 m off the query, 1 km out."""
    body = kind(
        name="q",
        part="forearm",
        a=np.array([0.0, 1.58987492e-160, -0.25]),
        b=np.array([0.0, 1.58987492e-160, 0.25]),
        radius_m=0.25,
    ).moved([1000.0, -1000.0, 1000.0])
    sp = body.closest_point(np.array([1000.0, -1000.0, 1000.0]))
    assert abs(np.linalg.norm(sp.normal) - 1.0) < 1e-12
    assert sp.distance_m == pytest.approx(-0.25)
