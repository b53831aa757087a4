"""Rotations and geometric fits: exactness, degenerate inputs, far-from-origin data, properties."""

from __future__ import annotations

import numpy as np
import pytest
from hapticloud.core.errors import InputError
from hapticloud.core.geometry.fits import circle3d, plane3d, sphere3d
from hapticloud.core.geometry.quadric import (
    NestedQuadricLSQ,
    QuadricPatch,
    local_quadric_closest,
    quadric_height,
    quadric_matrices,
    quadric_patch,
)
from hapticloud.core.geometry.rotations import (
    frame_from_unit_normal,
    orient_normal,
    orthonormal_frame,
    rotation_between,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FAR = np.array([1e3, -1e3, 1e3])

finite = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)
vectors = st.tuples(finite, finite, finite).map(np.array).filter(lambda v: np.linalg.norm(v) > 1e-3)
clouds = arrays(
    np.float64,
    st.tuples(st.integers(0, 40), st.just(3)),
    elements=st.one_of(
        st.floats(-1e3, 1e3), st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 1e-300])
    ),
)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _circle_points(center, normal, radius, n=40, arc=2 * np.pi, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    frame = frame_from_unit_normal(_unit(np.asarray(normal, float)))
    t = np.linspace(0.0, arc, n, endpoint=False)
    pts = np.asarray(center, float) + radius * (
        np.outer(np.cos(t), frame[:, 0]) + np.outer(np.sin(t), frame[:, 1])
    )
    return pts + noise * rng.normal(size=pts.shape)


def _sphere_points(center, radius, n=200, seed=0, cap_deg=180.0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n * 4, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d[:, 2] >= np.cos(np.radians(cap_deg))][:n]
    return np.asarray(center, float) + radius * d


# ----- rotations ---------------------------------------------------------------------------------


@SETTINGS
@given(vectors, vectors)
def test_rotation_between_maps_a_to_b_and_is_proper(a, b):
    rot = rotation_between(a, b)
    assert np.allclose(rot @ _unit(a), _unit(b), atol=1e-9)
    assert np.allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize(
    "a",
    [[1, 0, 0], [0, 0, 1], [0, 0, -1], [1, 2, 3], [1e-8, 0, 1], [0.6, -0.8, 0]],
)
def test_rotation_between_parallel_and_antiparallel(a):
    a = np.array(a, float)
    assert np.allclose(rotation_between(a, 3 * a), np.eye(3), atol=1e-12)
    for b in (-a, -a + 1e-9 * np.array([0.3, -0.2, 0.1])):
        rot = rotation_between(a, b)
        assert np.allclose(rot @ _unit(a), _unit(b), atol=1e-8)
        assert np.allclose(rot.T @ rot, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) == pytest.approx(1.0)


def test_rotation_between_rejects_zero_and_bad_shapes():
    with pytest.raises(InputError, match="a"):
        rotation_between([0, 0, 0], [1, 0, 0])
    with pytest.raises(ValueError, match="b"):
        rotation_between([1, 0, 0], [1, 0])
    with pytest.raises(ValueError, match="a"):
        rotation_between(["x", "y", "z"], [1, 0, 0])


@SETTINGS
@given(vectors)
def test_frames_are_right_handed_with_the_normal_last(n):
    n = _unit(n)
    for frame in (frame_from_unit_normal(n), orthonormal_frame(n)):
        assert np.allclose(frame.T @ frame, np.eye(3), atol=1e-12)
        assert np.linalg.det(frame) == pytest.approx(1.0)
        assert np.allclose(frame[:, 2], n, atol=1e-12)


def test_orient_normal_faces_the_camera_and_guards_edge_on_views():
    cam = np.array([0.0, 0.0, 1.0])  # looking along +z
    assert np.allclose(orient_normal([0, 0, 1], cam), [0, 0, -1])
    assert np.allclose(orient_normal([0, 0, -2], cam), [0, 0, -1])
    # Edge-on (n . z = 0): sign() would give 0; the HIP's side decides instead.
    hip, point = np.array([0.5, 0.0, 0.0]), np.zeros(3)
    assert np.allclose(orient_normal([1, 0, 0], cam, point, hip), [1, 0, 0])
    assert np.allclose(orient_normal([-1, 0, 0], cam, point, hip), [1, 0, 0])
    # Without a HIP the camera rule still returns a unit vector, never zero.
    assert np.linalg.norm(orient_normal([1, 0, 0], cam)) == pytest.approx(1.0)


# ----- plane -------------------------------------------------------------------------------------


def test_plane3d_exact_and_weighted():
    rng = np.random.default_rng(1)
    n = _unit(np.array([0.2, -0.3, 1.0]))
    frame = frame_from_unit_normal(n)
    uv = rng.uniform(-0.1, 0.1, size=(50, 2))
    pts = np.array([0.3, 0.1, 0.7]) + uv @ frame[:, :2].T
    fit = plane3d(pts)
    assert fit.valid and fit.n_points == 50
    assert abs(abs(fit.normal @ n) - 1.0) < 1e-12
    assert fit.rms_m < 1e-12
    assert np.allclose(fit.centroid, pts.mean(0))
    w = np.r_[np.ones(50), 0.0]  # a zero-weight outlier is ignored
    fit_w = plane3d(np.vstack((pts, [[5.0, 5.0, 5.0]])), w)
    assert fit_w.valid and abs(abs(fit_w.normal @ n) - 1.0) < 1e-12


@pytest.mark.parametrize(
    ("points", "reason"),
    [
        (np.empty((0, 3)), "no finite points"),
        (np.full((5, 3), np.nan), "no finite points"),
        ([[0, 0, 0], [1, 1, 1]], "3 points"),
        ([[1, 2, 3]] * 6, "coincide"),
        ([[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]], "collinear"),
        ([[0, 0, 0], [1, 1, 1], [np.nan, 0, 0], [np.inf, 1, 2]], "3 points"),
    ],
)
def test_plane3d_degenerate_inputs_are_flagged(points, reason):
    fit = plane3d(points)
    assert not fit.valid and reason in fit.reason
    assert np.all(np.isfinite(fit.centroid)) and np.all(np.isfinite(fit.normal))


def test_fits_reject_wrong_shapes_and_weights_naming_the_argument():
    good = np.zeros((4, 3))
    for fit in (plane3d, circle3d, sphere3d):
        with pytest.raises(ValueError, match="points"):
            fit(np.zeros((4, 2)))
        with pytest.raises(ValueError, match="points"):
            fit(np.array([["a", "b", "c"]]))
        with pytest.raises(ValueError, match="weights"):
            fit(good, np.ones(3))
        with pytest.raises(ValueError, match="weights"):
            fit(good, -np.ones(4))


# ----- circle ------------------------------------------------------------------------------------


@SETTINGS
@given(
    center=st.tuples(finite, finite, finite).map(np.array),
    normal=vectors,
    radius=st.floats(0.01, 2.0),
    arc=st.floats(0.5, 2 * np.pi),
)
def test_circle3d_recovers_exact_circles(center, normal, radius, arc):
    fit = circle3d(_circle_points(center, normal, radius, arc=arc))
    assert fit.valid, fit.reason
    assert np.allclose(fit.center, center, atol=1e-7 * (1 + radius))
    assert fit.radius_m == pytest.approx(radius, rel=1e-7)
    assert abs(abs(fit.normal @ _unit(normal)) - 1.0) < 1e-9


def test_circle3d_translates_with_far_data():
    pts = _circle_points([0.01, 0.02, 0.6], [0.1, 0.2, 1.0], 0.05, arc=2.0, noise=5e-4, seed=3)
    near, far = circle3d(pts), circle3d(pts + FAR)
    assert near.valid and far.valid
    assert np.allclose(far.center - FAR, near.center, atol=1e-6)
    assert far.radius_m == pytest.approx(near.radius_m, abs=1e-6)


def test_circle3d_straight_and_degenerate_sets_are_flagged_not_far_away():
    line = np.outer(np.linspace(0, 1, 20), [1.0, 2.0, 3.0])
    assert "collinear" in circle3d(line).reason
    # A nearly straight arc: radius 1e6 m seen over 10 cm. A centre 1e6 m away is useless.
    arc = _circle_points([0, 0, 0], [0, 0, 1], 1e6, n=30, arc=1e-7)
    fit = circle3d(arc)
    assert not fit.valid
    assert np.all(np.abs(fit.center) < 1e7) and np.all(np.isfinite(fit.center))
    assert not circle3d([[0, 0, 0], [1, 0, 0]]).valid
    assert not circle3d([[1, 1, 1]] * 10).valid


def test_circle3d_on_an_exactly_flat_annulus_finds_its_centre():
    """A shell cut from a plane: an annulus, coplanar to the last bit. Its centre is the foot."""
    rng = np.random.default_rng(0)
    r = np.sqrt(rng.uniform(0.03**2, 0.04**2, 300))
    t = rng.uniform(0, 2 * np.pi, 300)
    pts = np.column_stack((r * np.cos(t), r * np.sin(t), np.zeros(300))) + np.array([0.2, 0.1, 0.5])
    fit = circle3d(pts)
    assert fit.valid
    assert np.allclose(fit.center, [0.2, 0.1, 0.5], atol=2e-3)
    assert abs(fit.normal[2]) == pytest.approx(1.0)


def test_circle3d_duplicates_give_the_same_circle():
    pts = _circle_points([0, 0, 1], [0, 1, 1], 0.2, n=12)
    a, b = circle3d(pts), circle3d(np.vstack([pts, pts, pts]))
    assert a.valid and b.valid
    assert np.allclose(a.center, b.center, atol=1e-12)


# ----- sphere ------------------------------------------------------------------------------------


@SETTINGS
@given(
    center=st.tuples(finite, finite, finite).map(np.array),
    radius=st.floats(0.02, 3.0),
    cap=st.floats(40.0, 180.0),
)
def test_sphere3d_recovers_exact_spheres(center, radius, cap):
    fit = sphere3d(_sphere_points(center, radius, cap_deg=cap))
    assert fit.valid, fit.reason
    assert np.allclose(fit.center, center, atol=1e-6 * (1 + radius))
    assert fit.radius_m == pytest.approx(radius, rel=1e-6)


def test_sphere3d_noisy_far_and_degenerate():
    rng = np.random.default_rng(2)
    pts = _sphere_points([0.1, 0.0, 0.7], 0.09, n=800, cap_deg=60) + rng.normal(0, 1e-3, (800, 3))
    near, far = sphere3d(pts), sphere3d(pts + FAR)
    assert near.valid and far.valid
    assert np.allclose(near.center, [0.1, 0.0, 0.7], atol=5e-3)
    assert np.allclose(far.center - FAR, near.center, atol=1e-6)
    flat = _circle_points([0, 0, 0], [0, 0, 1], 1.0)
    assert "coplanar" in sphere3d(flat).reason
    assert not sphere3d(flat[:3]).valid
    assert not sphere3d(np.full((4, 3), np.nan)).valid


@SETTINGS
@given(clouds)
def test_fits_never_raise_or_return_nan_on_arbitrary_clouds(cloud):
    for fit in (plane3d(cloud), circle3d(cloud), sphere3d(cloud)):
        values = [v for v in vars(fit).values() if isinstance(v, np.ndarray | float)]
        assert all(np.all(np.isfinite(v)) for v in values)


# ----- quadric patch -----------------------------------------------------------------------------


def _local_sphere(radius, n=400, seed=0, hole=0.0, reach=2.5):
    """Points of a sphere tangent to z = 0 at the origin, curving away to -z (local units)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-reach, reach, size=(n * 3, 2))
    rr = (xy**2).sum(1)
    xy = xy[(rr < 0.8 * radius**2) & (rr >= hole**2)][:n]
    z = -(radius - np.sqrt(radius**2 - (xy**2).sum(1)))
    return np.column_stack((xy, z))


def test_nested_lsq_gives_every_model_from_one_factorisation():
    rng = np.random.default_rng(4)
    q = rng.normal(size=(300, 3))
    noise = 0.01 * rng.normal(size=300)
    q[:, 2] = 0.1 + 0.2 * q[:, 0] - 0.3 * q[:, 1] + 0.05 * q[:, 0] ** 2 + noise
    w = rng.uniform(0.5, 1.0, 300)
    lsq = NestedQuadricLSQ(q, w)
    sw = np.sqrt(w)
    for model, cols in (("plane", 3), ("paraboloid", 6)):
        coef, _ = lsq.solve(model)
        design = np.column_stack(
            [np.ones(300), q[:, 0], q[:, 1], q[:, 0] ** 2, q[:, 0] * q[:, 1], q[:, 1] ** 2][:cols]
        )
        ref = np.linalg.lstsq(design * sw[:, None], q[:, 2] * sw, rcond=None)
        assert np.allclose(coef[:cols], ref[0], atol=1e-10)
        assert lsq.rss(model) == pytest.approx(float(ref[1][0]), rel=1e-8)
    assert lsq.rss("plane") > lsq.rss("paraboloid") >= lsq.rss("quadric")


def test_quadric_patch_is_exact_on_a_sphere_even_with_a_hole_and_far_away():
    radius = 0.09
    q = _local_sphere(radius / 0.035, hole=0.04 / 0.035) * 0.035
    frame = frame_from_unit_normal(_unit(np.array([0.3, -0.2, 1.0])))
    origin = np.array([0.2, -0.1, 0.8])
    for offset in (np.zeros(3), FAR):
        pts = origin + offset + q @ frame.T
        hip = origin + offset + 0.07 * frame[:, 2]
        patch = quadric_patch(
            pts, origin=origin + offset, normal=frame[:, 2], model="spheroid", scale_m=0.035
        )
        assert patch.valid, patch.reason
        assert np.abs(patch.residuals(pts)).max() < 1e-9
        ok, closest, normal = patch.closest_point(hip)
        assert ok
        assert np.allclose(closest, origin + offset, atol=1e-7)
        assert np.allclose(normal, frame[:, 2], atol=1e-7)
    # The paraboloid is biased there: the hole hides the apex it would need.
    parab = quadric_patch(pts, origin=origin + FAR, normal=frame[:, 2], scale_m=0.035)
    assert np.linalg.norm(parab.closest_point(hip)[1] - origin - FAR) > 5e-4


def test_quadric_patch_on_flat_data_rejects_spurious_terms():
    rng = np.random.default_rng(5)
    pts = np.column_stack((rng.uniform(-0.1, 0.1, (500, 2)), 1e-3 * rng.normal(size=500)))
    for model in ("plane", "paraboloid", "spheroid", "quadric"):
        patch = quadric_patch(pts, origin=[0, 0, 0], normal=[0, 0, 1], model=model)
        if not patch.valid:
            assert "ill-conditioned" in patch.reason
            continue
        ok, closest, normal = patch.closest_point([0.0, 0.0, 0.05])
        assert ok and abs(closest[2]) < 1e-3 and normal[2] > 0.999


@pytest.mark.parametrize(
    "points", [np.empty((0, 3)), np.full((9, 3), np.nan), np.zeros((3, 3)), np.zeros((20, 3))]
)
def test_quadric_patch_degenerate_inputs(points):
    patch = quadric_patch(points, origin=[0, 0, 0], normal=[0, 0, 1], model="paraboloid")
    assert not patch.valid and patch.reason
    ok, closest, normal = patch.closest_point([0, 0, 1])
    assert not ok and np.all(np.isfinite(closest)) and np.all(np.isfinite(normal))
    with pytest.raises(InputError, match="model"):
        quadric_patch(points, origin=[0, 0, 0], normal=[0, 0, 1], model="cubic")
    with pytest.raises(ValueError, match="origin"):
        quadric_patch(points, origin=[0, 0], normal=[0, 0, 1])


@settings(max_examples=60, deadline=None)
@given(
    coef=arrays(np.float64, 9, elements=st.floats(-0.6, 0.6)),
    h=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0.3, 3.0)).map(np.array),
)
def test_closest_point_on_a_quadric_is_a_stationary_point_no_farther_than_its_neighbours(coef, h):
    found = local_quadric_closest(coef, h)
    if found is None:
        return
    q, n = found
    a, b, c = quadric_matrices(coef)
    assert abs(q @ a @ q + b @ q + c) < 1e-8 * (1 + np.abs(q).max() ** 2)
    assert np.linalg.norm(n) == pytest.approx(1.0)
    # Lagrange: h - q is parallel to the normal.
    d = h - q
    if np.linalg.norm(d) > 1e-9:
        assert np.linalg.norm(np.cross(d / np.linalg.norm(d), n)) < 1e-6
    # No surface point near q is closer to h (sample the surface around q along its heights).
    rng = np.random.default_rng(0)
    around = q + np.column_stack((rng.normal(0, 0.05, (200, 2)), np.zeros(200)))
    around[:, 2] = quadric_height(around, coef)
    on = np.abs(np.einsum("ij,jk,ik->i", around, a, around) + around @ b + c) < 1e-9
    assert np.all(np.linalg.norm(around[on] - h, axis=1) >= np.linalg.norm(d) - 1e-9)


def test_quadric_patch_frame_and_world_round_trip():
    patch = QuadricPatch(True, [1.0, 2.0, 3.0], np.eye(3), 0.5, "plane", np.zeros(9), 0.0, 1.0)
    assert np.allclose(patch.to_local([[1.0, 2.0, 3.5]]), [[0.0, 0.0, 1.0]])
    assert patch.residuals([[1.0, 2.0, 3.5]]) == pytest.approx([0.5])


def _explicit_leverage(w, cols, x0):
    a = np.column_stack(cols)
    return float(np.sqrt(x0 @ np.linalg.solve(a.T @ (a * w[:, None]), x0)))


def test_leverage_is_the_standard_error_of_the_fitted_height_per_unit_noise():
    rng = np.random.default_rng(3)
    q = rng.uniform(-1.0, 1.0, size=(300, 3))
    q[:, 2] = 0.2 * q[:, 0] ** 2 - 0.1 * q[:, 1] ** 2 + 0.01 * rng.normal(size=300)
    w = np.exp(-0.5 * np.einsum("ij,ij->i", q[:, :2], q[:, :2]))
    x, y = q[:, 0], q[:, 1]
    point = np.array([0.4, -0.3, 0.05])
    px, py, pz = point
    lsq = NestedQuadricLSQ(q, w, 6)
    explicit = _explicit_leverage(
        w,
        (np.ones(300), x, y, x * x, x * y, y * y),
        np.array([1, px, py, px * px, px * py, py * py]),
    )
    assert lsq.leverage("paraboloid", point) == pytest.approx(explicit, rel=1e-9)
    plane = _explicit_leverage(w, (np.ones(300), x, y), np.array([1, px, py]))
    assert lsq.leverage("plane", point) == pytest.approx(plane, rel=1e-9)
    # The z-terms use a prediction of z for the data, and the one given for the point.
    zhat = 0.2 * x * x
    full = NestedQuadricLSQ(q, w, 9, zhat)
    cols = (np.ones(300), x, y, x * x, x * y, y * y, zhat * zhat, x * zhat, y * zhat)
    row = np.array([1, px, py, px * px, px * py, py * py, pz * pz, px * pz, py * pz])
    assert full.leverage("quadric", point, pz) == pytest.approx(
        _explicit_leverage(w, cols, row), rel=1e-8
    )


def test_leverage_grows_where_the_fit_extrapolates_and_is_inf_when_it_cannot_fit():
    rng = np.random.default_rng(4)
    q = np.column_stack((rng.uniform(-1.0, 1.0, size=(400, 2)), np.zeros(400)))
    lsq = NestedQuadricLSQ(q, np.ones(400), 6)
    inside = lsq.leverage("paraboloid", np.array([0.0, 0.0, 0.0]))
    edge = lsq.leverage("paraboloid", np.array([1.0, 0.0, 0.0]))
    beyond = lsq.leverage("paraboloid", np.array([2.0, 0.0, 0.0]))
    assert inside < edge < beyond
    assert inside == pytest.approx(np.sqrt(6 / 400), rel=0.5)  # ~ sqrt(p / n) in the middle
    line = NestedQuadricLSQ(np.zeros((2, 3)), np.ones(2), 6)  # two points: no paraboloid
    assert lsq.leverage("quadric", np.zeros(3)) == np.inf  # not factorised (k_max 6)
    assert line.leverage("paraboloid", np.zeros(3)) == np.inf
