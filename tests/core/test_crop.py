"""Stage A (crop): world clouds and depth frames against brute force, degenerate input, configs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hapticloud.core.camera import CameraIntrinsics, DepthFrame, look_at
from hapticloud.core.errors import ConfigError, InputError
from hapticloud.core.geometry import Box, Capsule, Sphere, inside_any
from hapticloud.core.perception import CameraPipeline, PerceptionConfig
from hapticloud.core.perception.crop import (
    CropConfig,
    CropResult,
    _slope_range,
    crop_depth_frame,
    crop_points,
    hidden_length,
    sphere_region,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

HIP = np.array([0.1, -0.05, 1.2])


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


PRIMS = (
    Sphere(HIP + np.array([0.0, 0.0, 0.02]), 0.03),
    Capsule(HIP + np.array([0.0, 0.05, 0.0]), HIP + np.array([0.2, 0.3, 0.1]), 0.025),
    Box(HIP + np.array([-0.08, 0.0, 0.0]), [0.02, 0.04, 0.03], _rot_z(0.4)),
    Sphere(HIP + np.array([3.0, 0.0, 0.0]), 0.1),  # far away: pruned, must not matter
)


def brute_force(points: np.ndarray, hip: np.ndarray, prims, cfg: CropConfig):
    p = np.asarray(points, dtype=np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    inside = np.linalg.norm(p - hip, axis=1) < cfg.workspace_radius_m
    p = p[inside]
    robot = inside_any(p, list(prims), cfg.exclude_margin_m) if prims else np.zeros(len(p), bool)
    return p[~robot], p[robot]


def same_rows(a: np.ndarray, b: np.ndarray, atol: float = 0.0) -> bool:
    if a.shape != b.shape:
        return False
    if a.size == 0:
        return True
    ka = a[np.lexsort(a.T[::-1])]
    kb = b[np.lexsort(b.T[::-1])]
    return bool(np.allclose(ka, kb, atol=atol, rtol=0.0))


def random_cloud(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return HIP + rng.uniform(-0.4, 0.4, (n, 3))


# ----- config -----------------------------------------------------------------------------------


def test_config_defaults_and_ranges() -> None:
    cfg = CropConfig()
    assert 0.1 <= cfg.workspace_radius_m <= 0.2
    assert cfg.exclude_margin_m == pytest.approx(0.01)
    with pytest.raises(ConfigError, match="workspace_radius_m"):
        CropConfig(workspace_radius_m=0.0)
    with pytest.raises(ConfigError, match="exclude_margin_m"):
        CropConfig(exclude_margin_m=-0.001)
    with pytest.raises(ConfigError, match=r"min_depth_m.*max_depth_m"):
        CropConfig(min_depth_m=2.0, max_depth_m=1.0)
    assert CropConfig.from_dict({"workspace_radius_m": 0.2}).workspace_radius_m == 0.2


# ----- world clouds -------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [50_000, 70_001])  # several chunks, ragged last chunk
def test_crop_points_matches_brute_force(n: int) -> None:
    pts = random_cloud(n)
    cfg = CropConfig()
    res = crop_points(pts, HIP, PRIMS, cfg)
    kept, robot = brute_force(pts, HIP, PRIMS, cfg)
    assert isinstance(res, CropResult)
    assert res.points.dtype == np.float64 and res.points.flags.c_contiguous
    assert same_rows(res.points, kept)
    assert same_rows(res.removed_robot, robot)
    assert res.n_input == n
    assert res.n_in_workspace == len(kept) + len(robot)
    assert res.n_outside == n - res.n_in_workspace
    assert res.n_kept == len(kept) and res.n_robot == len(robot) > 0


def test_crop_points_float32_without_upcasting_the_input() -> None:
    pts32 = random_cloud(40_000, seed=1).astype(np.float32)
    res = crop_points(pts32, HIP, PRIMS)
    kept, robot = brute_force(pts32.astype(np.float64), HIP, PRIMS, CropConfig())
    assert res.points.dtype == np.float64
    assert same_rows(res.points, kept)
    assert same_rows(res.removed_robot, robot)


def test_crop_points_nan_and_inf_rows_are_dropped() -> None:
    pts = random_cloud(5000, seed=2)
    pts[::7, 1] = np.nan
    pts[::11, 2] = np.inf
    pts[::13, 0] = -np.inf
    pts[5] = HIP + np.array([np.nan, 0.0, 0.0])  # NaN right at the HIP
    res = crop_points(pts, HIP, PRIMS)
    kept, _ = brute_force(pts, HIP, PRIMS, CropConfig())
    assert np.isfinite(res.points).all() and np.isfinite(res.removed_robot).all()
    assert same_rows(res.points, kept)


@pytest.mark.parametrize(
    "points",
    [
        np.empty((0, 3)),
        np.empty(0),
        np.full((10, 3), np.nan),
        np.full((3, 3), np.inf),
    ],
    ids=["empty", "empty-1d", "all-nan", "all-inf"],
)
def test_crop_points_degenerate_inputs_give_empty_results(points: np.ndarray) -> None:
    res = crop_points(points, HIP, PRIMS)
    assert res.points.shape == (0, 3) and res.removed_robot.shape == (0, 3)
    assert res.n_in_workspace == 0


def test_crop_points_single_points() -> None:
    assert crop_points([HIP + np.array([0.0, 0.0, 0.1])], HIP, ()).n_kept == 1
    assert crop_points([HIP + np.array([0.0, 0.0, 0.2])], HIP, ()).n_kept == 0
    res = crop_points([HIP + np.array([0.0, 0.0, 0.02])], HIP, PRIMS)  # inside the first sphere
    assert res.n_kept == 0 and res.n_robot == 1
    # Integer input is accepted.
    assert crop_points(np.array([[0, 0, 1]]), [0, 0, 1], None).n_kept == 1


def test_crop_points_margin_grows_the_primitives() -> None:
    link = Sphere(HIP, 0.05)
    pts = HIP + np.array([[0.055, 0.0, 0.0], [0.065, 0.0, 0.0]])
    assert crop_points(pts, HIP, [link], CropConfig(exclude_margin_m=0.0)).n_kept == 2
    res = crop_points(pts, HIP, [link], CropConfig(exclude_margin_m=0.01))
    assert res.n_kept == 1 and res.n_robot == 1
    assert crop_points(pts, HIP, link, CropConfig(exclude_margin_m=0.01)).n_kept == 1


def test_crop_points_primitive_touching_the_sphere_edge_is_applied() -> None:
    # A big box whose centre is far outside the workspace but which reaches into it.
    box = Box(HIP + np.array([0.5, 0.0, 0.0]), [0.38, 0.3, 0.3])
    pts = HIP + np.array([[0.13, 0.0, 0.0], [0.11, 0.0, 0.0]])
    res = crop_points(pts, HIP, [box], CropConfig(exclude_margin_m=0.0))
    assert res.n_kept == 1 and res.n_robot == 1


def test_crop_points_input_errors_name_the_argument() -> None:
    with pytest.raises(ValueError, match="points_world"):
        crop_points(np.zeros((4, 2)), HIP, ())
    with pytest.raises(ValueError, match="points_world"):
        crop_points(np.array([["a", "b", "c"]]), HIP, ())
    with pytest.raises(InputError, match="hip"):
        crop_points(np.zeros((4, 3)), [0.0, 0.0], ())
    with pytest.raises(InputError, match="hip"):
        crop_points(np.zeros((4, 3)), [0.0, np.nan, 0.0], ())
    with pytest.raises(InputError, match="exclude"):
        crop_points(np.zeros((4, 3)), HIP, ["not a primitive"])


def test_crop_result_arrays_are_read_only() -> None:
    res = crop_points(random_cloud(1000), HIP, PRIMS)
    with pytest.raises(ValueError):
        res.points[0, 0] = 1.0


coord = st.floats(-0.3, 0.3, allow_nan=False, width=64)
point_rows = hnp.arrays(
    np.float64,
    st.tuples(st.integers(0, 60), st.just(3)),
    elements=st.one_of(coord, st.just(np.nan), st.just(0.15), st.just(-0.15)),
)
prim_st = st.one_of(
    st.builds(
        lambda c, r: Sphere(np.array(c), r),
        st.tuples(coord, coord, coord),
        st.floats(0.005, 0.2),
    ),
    st.builds(
        lambda a, b, r: Capsule(np.array(a), np.array(b), r),
        st.tuples(coord, coord, coord),
        st.tuples(coord, coord, coord),
        st.floats(0.005, 0.1),
    ),
    st.builds(
        lambda c, h, ang: Box(np.array(c), np.array(h), _rot_z(ang)),
        st.tuples(coord, coord, coord),
        st.tuples(st.floats(0.005, 0.1), st.floats(0.005, 0.1), st.floats(0.005, 0.1)),
        st.floats(-3.0, 3.0),
    ),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    points=point_rows,
    hip=st.tuples(coord, coord, coord),
    radius=st.floats(0.01, 0.4),
    margin=st.floats(0.0, 0.05),
    prims=st.lists(prim_st, max_size=3),
    as32=st.booleans(),
)
def test_crop_points_properties(points, hip, radius, margin, prims, as32) -> None:
    cfg = CropConfig(workspace_radius_m=radius, exclude_margin_m=margin)
    pts = points.astype(np.float32) if as32 else points
    res = crop_points(pts, hip, prims, cfg)
    h = np.array(hip)
    ref = pts.astype(np.float64)
    finite = ref[np.isfinite(ref).all(axis=1)]
    # Subset of the input, and every kept point inside the sphere and outside the grown robot.
    rows = {tuple(r) for r in finite}
    assert all(tuple(r) in rows for r in res.points)
    assert all(tuple(r) in rows for r in res.removed_robot)
    assert np.all(np.linalg.norm(res.points - h, axis=1) < radius * (1 + 1e-12))
    assert np.all(np.linalg.norm(res.removed_robot - h, axis=1) < radius * (1 + 1e-12))
    if prims and res.n_kept:
        assert not inside_any(res.points, prims, margin - 1e-9).any()
    if prims and res.n_robot:
        assert inside_any(res.removed_robot, prims, margin + 1e-9).all()
    # Nothing clearly inside the workspace and clearly outside the robot is lost.
    d = np.linalg.norm(finite - h, axis=1)
    clear = finite[d < radius * (1 - 1e-9)]
    if prims:
        clear = clear[~inside_any(clear, prims, margin + 1e-9)]
    assert res.n_kept >= len(clear)
    assert res.n_kept + res.n_robot == res.n_in_workspace <= len(finite)


# ----- depth frames -------------------------------------------------------------------------------

SMALL_K = CameraIntrinsics.d435(width=212, height=120)


def render(
    k: CameraIntrinsics,
    pose: np.ndarray,
    spheres: list[tuple[np.ndarray, float]],
    wall_z_cam: float | None = 1.0,
) -> np.ndarray:
    """Analytic depth (z along the view axis) of spheres given in the world and a fronto wall."""
    xs, ys = (a.astype(np.float64) for a in k.pixel_rays())
    z = np.full(xs.shape, np.inf)
    rot, t = pose[:3, :3], pose[:3, 3]
    for center, radius in spheres:
        c = rot.T @ (np.asarray(center, float) - t)
        rc = xs * c[0] + ys * c[1] + c[2]
        rr = xs * xs + ys * ys + 1.0
        disc = rc * rc - rr * (c @ c - radius * radius)
        hit = disc >= 0
        zs = np.full(xs.shape, np.inf)
        zs[hit] = (rc[hit] - np.sqrt(disc[hit])) / rr[hit]
        zs[zs <= 0] = np.inf
        z = np.minimum(z, zs)
    if wall_z_cam is not None:
        z = np.minimum(z, wall_z_cam)
    z[~np.isfinite(z)] = 0.0
    return z.astype(np.float32)


def scene_frame(seed: int = 0, hip_offset: float = 0.06):
    eye = np.array([0.7, 0.05, 1.3])
    head = np.array([0.0, 0.0, 1.2])
    pose = look_at(eye, head)
    direction = np.array([1.0, -0.5, 0.3]) / np.linalg.norm([1.0, -0.5, 0.3])
    hip = head + (0.09 + hip_offset) * direction
    depth = render(SMALL_K, pose, [(head, 0.09), (hip, 0.04)], wall_z_cam=1.0)
    rng = np.random.default_rng(seed)
    depth = depth + rng.normal(0, 0.001, depth.shape).astype(np.float32) * (depth > 0)
    depth[rng.random(depth.shape) < 0.02] = 0.0
    depth[rng.random(depth.shape) < 0.01] = np.nan
    return DepthFrame(0.0, "cam", depth, SMALL_K, pose), hip, (Sphere(hip, 0.04),)


def test_crop_depth_frame_matches_full_deprojection() -> None:
    frame, hip, prims = scene_frame()
    cfg = CropConfig()
    res = crop_depth_frame(frame, hip, prims, cfg)
    kept, robot = brute_force(frame.points_world(), hip, prims, cfg)
    assert res.n_input == SMALL_K.width * SMALL_K.height
    assert res.region is not None
    r0, r1, c0, c1 = res.region
    assert (r1 - r0) * (c1 - c0) < 0.5 * res.n_input  # a real cut, not the whole image
    assert len(kept) > 300 and len(robot) > 50
    # points_world deprojects in float32: equal up to float32 rounding of x*z.
    assert same_rows(res.points, kept, atol=1e-6)
    assert same_rows(res.removed_robot, robot, atol=1e-6)
    assert np.isfinite(res.points).all()


def test_crop_depth_frame_float64_depth_and_depth_limits() -> None:
    frame, hip, prims = scene_frame(seed=1)
    f64 = DepthFrame(0.0, "cam", frame.depth_m.astype(np.float64), SMALL_K, frame.pose_world_camera)
    res = crop_depth_frame(f64, hip, prims)
    assert same_rows(res.points, crop_depth_frame(frame, hip, prims).points, atol=1e-6)
    # A max depth in front of the whole workspace: nothing.
    cam_dist = float(np.linalg.norm(hip - frame.origin_world))
    none = crop_depth_frame(frame, hip, prims, CropConfig(min_depth_m=0.05, max_depth_m=0.2))
    assert cam_dist > 0.5 and none.n_kept == 0 and none.region is None


def _frame_at_origin(depth: np.ndarray) -> DepthFrame:
    return DepthFrame(0.0, "cam", depth.astype(np.float32), SMALL_K, np.eye(4))


def test_crop_depth_frame_sphere_behind_camera_is_empty() -> None:
    depth = np.full((SMALL_K.height, SMALL_K.width), 0.8, np.float32)
    res = crop_depth_frame(_frame_at_origin(depth), [0.0, 0.0, -0.5], ())
    assert res.n_kept == 0 and res.region is None and res.n_input == depth.size


@pytest.mark.parametrize(
    "hip",
    [
        [0.0, 0.0, 0.05],  # camera inside the workspace sphere (partly behind the camera)
        [0.0, 0.0, -0.1],  # centre behind the camera, the front cap still in view
        [0.6, 0.0, 0.5],  # beyond the right image border
        [0.25, -0.2, 0.4],  # a corner
    ],
)
def test_crop_depth_frame_partial_views_match_brute_force(hip) -> None:
    k = SMALL_K
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.002, 0.7, (k.height, k.width)).astype(np.float32)
    frame = _frame_at_origin(depth)
    cfg = CropConfig(min_depth_m=0.001)
    res = crop_depth_frame(frame, hip, (), cfg)
    kept, _ = brute_force(frame.points_world(), np.array(hip, float), (), cfg)
    kept = kept[kept[:, 2] >= cfg.min_depth_m]
    assert len(kept) > 0
    assert same_rows(res.points, kept, atol=1e-6)


def test_crop_depth_frame_invalid_pixels_and_errors() -> None:
    k = SMALL_K
    depth = np.zeros((k.height, k.width), np.float32)
    depth[::2] = np.nan
    res = crop_depth_frame(_frame_at_origin(depth), [0.0, 0.0, 0.6], ())
    assert res.n_kept == 0 and res.points.shape == (0, 3)
    one = np.zeros((k.height, k.width), np.float32)
    one[k.height // 2, k.width // 2] = 0.6
    assert crop_depth_frame(_frame_at_origin(one), [0.0, 0.0, 0.6], ()).n_kept == 1
    with pytest.raises(InputError, match="frame"):
        crop_depth_frame(np.zeros((4, 3)), [0.0, 0.0, 0.6], ())  # type: ignore[arg-type]
    with pytest.raises(InputError, match="hip"):
        crop_depth_frame(_frame_at_origin(one), [0.0, 0.6], ())


def test_sphere_region_clips_to_the_image() -> None:
    frame = _frame_at_origin(np.ones((SMALL_K.height, SMALL_K.width)))
    full = sphere_region(frame, [0.0, 0.0, 0.05], 0.15, 0.01, 4.0)
    assert full is not None and full[:4] == (0, SMALL_K.height, 0, SMALL_K.width)
    assert sphere_region(frame, [10.0, 0.0, 0.5], 0.15, 0.01, 4.0) is None  # far off to the side


@settings(max_examples=200, deadline=None)
@given(
    cx=st.floats(-1.0, 1.0),
    cz=st.floats(-0.5, 1.5),
    r=st.floats(0.01, 0.5),
    zlo=st.floats(0.001, 0.8),
    dz=st.floats(0.01, 2.0),
)
def test_slope_range_bounds_every_ball_point(cx, cz, r, zlo, dz) -> None:
    zhi = zlo + dz
    rng = np.random.default_rng(0)
    ang = rng.uniform(0, 2 * np.pi, 400)
    rad = r * np.sqrt(rng.uniform(0, 1, 400))
    x = np.r_[cx + rad * np.cos(ang), cx + r * np.cos(ang)]
    z = np.r_[cz + rad * np.sin(ang), cz + r * np.sin(ang)]
    ok = (z >= zlo) & (z <= zhi)
    found = _slope_range(cx, cz, r, zlo, zhi)
    if not ok.any():
        return
    assert found is not None
    s = x[ok] / z[ok]
    tol = 1e-9 * (1 + np.abs(s))
    assert np.all(s >= found[0] - tol) and np.all(s <= found[1] + tol)


def test_hidden_length_is_the_margin_a_segment_crosses() -> None:
    ball = Sphere(HIP, 0.035)
    down = HIP - np.array([0.0, 0.0, 0.1])
    # Straight out of the ball: it crosses the whole margin, and nothing more.
    assert hidden_length(HIP, down, (ball,), 0.02) == pytest.approx(0.02, abs=3e-4)
    assert hidden_length(HIP, down, (ball,), 0.0) == 0.0
    assert hidden_length(HIP, down, (), 0.02) == 0.0
    # Ending inside the margin: only the part of the margin it reaches.
    inside = HIP - np.array([0.0, 0.0, 0.045])
    assert hidden_length(HIP, inside, (ball,), 0.05) == pytest.approx(0.01, abs=3e-4)
    # Passing a box at 5 mm: within a 1 cm margin along its 4 cm face and the rounded edges.
    box = Box(HIP + np.array([0.0, 0.025, 0.0]), [0.02, 0.02, 0.02])
    a, b = HIP + np.array([-0.05, 0.0, 0.0]), HIP + np.array([0.05, 0.0, 0.0])
    edges = 2.0 * math.sqrt(0.01**2 - 0.005**2)
    assert hidden_length(a, b, (box,), 0.01) == pytest.approx(0.04 + edges, abs=3e-4)
    assert hidden_length(a, b, (box,), 0.004) == 0.0


def _head_cloud(radius: float = 0.09) -> np.ndarray:
    rng = np.random.default_rng(0)
    v = rng.normal(size=(60000, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    return radius * v[v[:, 2] > 0.0]


@pytest.mark.parametrize("margin", [0.01, 0.03, 0.05, 0.07, 0.1])
def test_a_wide_exclusion_margin_never_reports_the_surface_farther(margin: float) -> None:
    # The end effector's ball at the HIP and its handle, grown by the margin, swallow the surface
    # nearest to the HIP once the margin reaches it; the fit then bridged the hole from farther
    # points and reported the surface up to 72 mm farther than it is (margin 0.1 m, HIP 4 cm
    # from a 9 cm head). An estimate must be within the perception budget or invalid, saying why.
    cloud = _head_cloud()
    cfg = PerceptionConfig().replace_path("crop.exclude_margin_m", margin)
    valid = 0
    for d in (0.04, 0.06, 0.08, 0.1, 0.11):
        hip = np.array([0.0, 0.0, 0.09 + d])
        exclude = (Sphere(hip, 0.035), Capsule(hip, hip + np.array([0.0, 0.135, 0.27]), 0.025))
        est = CameraPipeline(cfg).process(cloud, hip, [0.0, 0.0, -1.0], exclude=exclude)
        if est.valid:
            valid += 1
            assert np.linalg.norm(est.centroid - hip) - d < 0.005
        else:
            assert "crop.exclude_margin_m" in est.reason
    if margin <= 0.03:  # no more of the way hidden than the pipeline accepts unseen elsewhere
        assert valid == 5


def test_a_workspace_inside_the_grown_robot_is_not_seen_empty() -> None:
    # A wall 0.1 m from the HIP, its ball grown by 0.1 m past the whole workspace: every wall
    # point is removed with the robot, and "seen empty" would prove 0.13 m free.
    wall = np.full((SMALL_K.height, SMALL_K.width), 0.6, np.float32)
    hip = np.array([0.0, 0.0, 0.5])
    cfg = PerceptionConfig().with_overrides(
        {
            "abstraction.r_out_m": 0.12,
            "crop.workspace_radius_m": 0.13,
            "crop.exclude_margin_m": 0.1,
        }
    )
    est = CameraPipeline(cfg).process_depth(_frame_at_origin(wall), hip, (Sphere(hip, 0.035),))
    assert not est.valid and est.free_m == 0.0
    assert "crop.exclude_margin_m" in est.reason
    seen = CameraPipeline(cfg).process_depth(_frame_at_origin(wall), hip, ())
    assert seen.valid  # the same wall without the robot
