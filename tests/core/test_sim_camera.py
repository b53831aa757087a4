"""Simulated D435: ray-cast accuracy, noise statistics, occluders, seeds, scenes, config errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hapticloud.core.camera import CameraIntrinsics, DepthFrame, look_at
from hapticloud.core.errors import ConfigError, InputError
from hapticloud.core.geometry import Capsule, Sphere
from hapticloud.core.sim import world as world_module
from hapticloud.core.sim.bodies import BoxBody, SphereBody
from hapticloud.core.sim.depth_camera import MISS, OCCLUDER, DepthNoiseConfig, SimDepthCamera
from hapticloud.core.sim.scenes import demo_scene, end_effector, perception_bench_scenes
from hapticloud.core.sim.world import SimWorld

K = CameraIntrinsics.d435()
NOISELESS = DepthNoiseConfig.noiseless()


def _wall_world(z: float) -> tuple[SimWorld, SimDepthCamera]:
    """A wall facing a camera at the origin looking along +x, its face at depth ``z``."""
    wall = BoxBody(
        name="wall", part="background", center=[z + 0.05, 0, 0], half_extents_m=[0.05, 5, 5]
    )
    dummy = SphereBody(name="far", part="chest", center=[-5.0, 0, 0], radius_m=0.1)  # behind
    return SimWorld([dummy], [wall]), SimDepthCamera("cam", K, look_at([0, 0, 0], [1, 0, 0]))


def _pixel_dirs(cam: SimDepthCamera) -> np.ndarray:
    k = cam.intrinsics
    xs, ys = k.pixel_rays()
    local = np.stack((xs, ys, np.ones_like(xs)), axis=-1).astype(np.float64)
    return local @ cam.pose_world_camera[:3, :3].T


@pytest.fixture(scope="module")
def scenes():
    return perception_bench_scenes()


# ----- geometry of the ideal image -------------------------------------------------------------


def _target_errors(scene, cam: SimDepthCamera, world: SimWorld):
    hits = cam.trace(world, incidence=True)
    target = world.surfaces.index(world.body(scene.target))
    on_target = hits.label == target
    t_exact, _ = world.body(scene.target).intersect_rays(
        cam.origin_world, _pixel_dirs(cam)[on_target]
    )
    return hits, on_target, hits.depth_m[on_target] - t_exact


@pytest.mark.parametrize("name", ["sphere_head", "ellipsoid_head", "cylinder_arm", "tilted_torso"])
def test_mesh_depth_is_within_tolerance_of_analytic_intersection(scenes, name: str) -> None:
    """The inscribed mesh alone (no closed-form refinement): the brief's < 0.05 mm at head size."""
    scene = scenes[name]
    cam = scene.cameras[0].with_noise(NOISELESS)
    world = scene.world.with_exact_depth(False)
    hits, on_target, err = _target_errors(scene, cam, world)
    assert on_target.sum() > 5000
    assert np.all(np.isfinite(err))  # the inscribed mesh never sticks out of the body
    head_on = hits.cos_incidence[on_target] > math.cos(math.radians(75))
    assert np.abs(err[head_on]).max() < 5e-5
    assert np.percentile(np.abs(err), 99) < 1e-4
    assert err.min() > -2e-6  # inscribed: never in front of the true surface (float32 aside)
    # Pixels the analytic body covers but the mesh does not: only at the silhouette.
    t_all, _ = world.body(scene.target).intersect_rays(
        cam.origin_world, _pixel_dirs(cam).reshape(-1, 3)
    )
    t_all = t_all.reshape(on_target.shape)
    covered = np.isfinite(t_all) & (t_all < hits.depth_m)
    assert (covered & ~on_target).sum() < 0.01 * on_target.sum()


@pytest.mark.parametrize("name", ["sphere_head", "ellipsoid_head", "cylinder_arm"])
def test_exact_depth_matches_analytic_intersection_everywhere(scenes, name: str) -> None:
    scene = scenes[name]
    cam = scene.cameras[1].with_noise(NOISELESS)
    _, on_target, err = _target_errors(scene, cam, scene.world)
    assert on_target.sum() > 5000
    assert np.abs(err).max() < 1e-6  # float32 depth, grazing silhouette pixels included


def test_wall_depth_is_exact_and_labels_are_right() -> None:
    world, cam = _wall_world(0.8)
    cam = cam.with_noise(NOISELESS)
    depth = cam.ideal_depth(world)
    np.testing.assert_allclose(depth, 0.8, atol=1e-6)
    hits = cam.trace(world)
    assert np.all(hits.label == 1)  # surfaces = bodies + background: the wall is index 1
    frame = cam.render(world)
    assert isinstance(frame, DepthFrame) and frame.depth_m.dtype == np.float32
    pts = frame.points_world()
    np.testing.assert_allclose(pts[:, 0], 0.8, atol=1e-6)


def test_miss_pixels_are_zero_and_labelled_miss() -> None:
    ball = SphereBody(name="ball", part="skull_forehead", center=[1.0, 0, 0], radius_m=0.1)
    cam = SimDepthCamera("cam", K, look_at([0, 0, 0], [1, 0, 0]), NOISELESS)
    world = SimWorld([ball])
    hits = cam.trace(world)
    assert (hits.label == MISS).mean() > 0.9
    depth = cam.ideal_depth(world)
    assert np.all(depth[hits.label == MISS] == 0)
    assert 0.97 < depth.max() <= 0.99  # the silhouette: tangent points at z = d - R^2 / d
    # nearest pixel is half a pixel off the axis; the mesh is within 1e-5 m
    assert depth[depth > 0].min() == pytest.approx(0.9, abs=3e-5)


def test_render_points_lie_on_the_surfaces(scenes) -> None:
    scene = scenes["ellipsoid_head"]
    cam = scene.cameras[1].with_noise(NOISELESS)
    pts = cam.render_points(scene.world)
    rng = np.random.default_rng(0)
    some = pts[rng.choice(len(pts), 400, replace=False)]
    d = [min(abs(b.closest_point(p).distance_m) for b in scene.world.surfaces) for p in some]
    assert max(d) < 2e-4  # a grazing pixel errs by tol / cos; most are far below
    assert np.median(d) < 1e-5


def test_moving_body_and_scene_cache_reuse() -> None:
    ball = SphereBody(
        name="ball",
        part="skull_forehead",
        center=[1.0, 0, 0],
        radius_m=0.1,
        velocity_mps=[-0.3, 0.0, 0.0],
    )
    cam = SimDepthCamera("cam", K, look_at([0, 0, 0], [1, 0, 0]), NOISELESS)
    world = SimWorld([ball])
    centre = (K.height // 2, K.width // 2)
    assert cam.ideal_depth(world, t=0.0)[centre] == pytest.approx(0.9, abs=3e-5)
    assert cam.ideal_depth(world, t=1.0)[centre] == pytest.approx(0.6, abs=3e-5)
    moved = world.moved("ball", [0.1, 0.0, 0.0])
    n_cached = len(world_module._SCENE_CACHE)
    assert cam.ideal_depth(moved, t=1.0)[centre] == pytest.approx(0.7, abs=3e-5)
    farther = world.moved("ball", [0.2, 0, 0])
    assert cam.ideal_depth(farther, t=1.0)[centre] == pytest.approx(0.8, abs=3e-5)
    assert len(world_module._SCENE_CACHE) == n_cached  # same shape: no new BVH


# ----- occluders -------------------------------------------------------------------------------


def test_occluders_hide_pixels_with_exact_depth(scenes) -> None:
    scene = scenes["sphere_head_occluded"]
    cam = scene.cameras[0].with_noise(NOISELESS)
    hip = scene.sample_hips(1, seed=11, max_view_angle_deg=15).hips[0]
    occ = scene.occluders(hip)
    assert isinstance(occ[0], Sphere) and isinstance(occ[1], Capsule)
    free = cam.trace(scene.world)
    hidden = cam.trace(scene.world, occluders=occ)
    by_robot = hidden.label == OCCLUDER
    assert by_robot.sum() > 1000
    assert np.all(hidden.depth_m[by_robot] < free.depth_m[by_robot])
    # The true closest point, seen almost head-on, is behind the end effector's ball.
    gt = scene.world.ground_truth(hip)
    ((u, v),) = np.rint(cam.project(gt.point[None])[0]).astype(int)
    assert hidden.label[v, u] == OCCLUDER and free.label[v, u] == 0
    # Depth of the robot's pixels equals the closed-form hit of the primitives.
    dirs = _pixel_dirs(cam)[by_robot]
    t_ball, _ = world_module.intersect_primitive(occ[0], cam.origin_world, dirs)
    t_handle, _ = world_module.intersect_primitive(occ[1], cam.origin_world, dirs)
    np.testing.assert_allclose(hidden.depth_m[by_robot], np.minimum(t_ball, t_handle), atol=1e-6)
    np.testing.assert_array_equal(hidden.label[~by_robot], free.label[~by_robot])


def test_end_effector_shape() -> None:
    ball, handle = end_effector([0, 0, 1], [2, 0, 0], handle_length_m=0.3)
    np.testing.assert_allclose(handle.b, [0.3, 0, 1])
    assert ball.radius == 0.035
    with pytest.raises(InputError, match="direction"):
        end_effector([0, 0, 1], [0, 0, 0])


# ----- noise -----------------------------------------------------------------------------------


@pytest.mark.parametrize("z", [0.6, 2.0])
def test_noise_std_matches_config(z: float) -> None:
    world, cam = _wall_world(z)
    cfg = DepthNoiseConfig(
        quantisation_m=0.0,
        dropout_fraction=0.0,
        grazing_dropout=0.0,
        flying_pixel_probability=0.0,
        seed=3,
    )
    depth = cam.with_noise(cfg).render(world).depth_m
    err = depth[depth > 0].astype(np.float64) - z
    sigma = cfg.sigma_base_m + cfg.sigma_z2_m_per_m2 * z * z
    assert err.size == K.width * K.height
    assert abs(err.std() / sigma - 1) < 0.1
    assert abs(err.mean()) < 0.05 * sigma


def test_quantisation_to_one_millimetre() -> None:
    world, cam = _wall_world(0.8)
    depth = cam.with_noise(DepthNoiseConfig(seed=1)).render(world).depth_m
    valid = depth[depth > 0].astype(np.float64)
    steps = valid / 0.001
    assert np.abs(steps - np.rint(steps)).max() < 1e-3
    assert len(np.unique(np.rint(steps))) > 5  # noise spreads over several steps


def test_dropout_fraction_and_grazing_dropouts() -> None:
    world, cam = _wall_world(0.8)
    cfg = DepthNoiseConfig(dropout_fraction=0.05, grazing_dropout=0.0, seed=2)
    depth = cam.with_noise(cfg).render(world).depth_m
    assert (depth == 0).mean() == pytest.approx(0.05, abs=0.003)
    # A wall seen at ~80 deg incidence loses many more pixels when grazing dropouts are on.
    wall = BoxBody(name="wall", part="background", center=[1.0, 0, 0], half_extents_m=[3, 3, 0.05])
    far = SphereBody(name="far", part="chest", center=[-5, 0, 0], radius_m=0.1)
    world = SimWorld([far], [wall])
    eye = np.array([1.0, 0.0, 0.25])
    down_10deg = np.array([math.cos(math.radians(10)), 0.0, -math.sin(math.radians(10))])
    cam = SimDepthCamera("cam", K, look_at(eye, eye + down_10deg))
    base = DepthNoiseConfig.noiseless(dropout_fraction=0.02, grazing_dropout=0.0)
    hits = cam.trace(world, incidence=True)
    seen = hits.label >= 0
    grazing = seen & (hits.cos_incidence < math.cos(math.radians(75)))
    assert grazing.sum() > 10000
    plain = cam.with_noise(base).render(world).depth_m
    more = (
        cam.with_noise(
            DepthNoiseConfig.noiseless(
                dropout_fraction=0.02, grazing_dropout=0.5, grazing_start_deg=65
            )
        )
        .render(world)
        .depth_m
    )
    assert (plain[grazing] == 0).mean() == pytest.approx(0.02, abs=0.01)
    assert (more[grazing] == 0).mean() > 0.15


def test_flying_pixels_sit_between_foreground_and_background() -> None:
    ball = SphereBody(name="ball", part="skull_forehead", center=[0.8, 0, 0], radius_m=0.1)
    wall = BoxBody(name="wall", part="background", center=[1.55, 0, 0], half_extents_m=[0.05, 5, 5])
    world = SimWorld([ball], [wall])
    cam = SimDepthCamera("cam", K, look_at([0, 0, 0], [1, 0, 0]))
    ideal = cam.with_noise(NOISELESS).ideal_depth(world)
    flying = cam.with_noise(DepthNoiseConfig.noiseless(flying_pixel_probability=1.0)).render(world)
    changed = np.abs(flying.depth_m - ideal) > 1e-6
    assert 200 < changed.sum() < 3000  # a ring of pixels around the ball's silhouette
    assert np.all((flying.depth_m[changed] > 0.7) & (flying.depth_m[changed] < 1.5))
    between = (flying.depth_m[changed] > ideal[changed] + 0.01) | (
        flying.depth_m[changed] < ideal[changed] - 0.01
    )
    assert between.mean() > 0.5
    none = cam.with_noise(DepthNoiseConfig.noiseless(flying_pixel_probability=0.0)).render(world)
    np.testing.assert_array_equal(none.depth_m, ideal)


def test_seeded_frames_are_reproducible_and_vary_with_time_and_seed() -> None:
    world, cam = _wall_world(0.8)
    a = cam.render(world, t=0.5).depth_m
    b = SimDepthCamera("cam", K, look_at([0, 0, 0], [1, 0, 0])).render(world, t=0.5).depth_m
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, cam.render(world, t=0.5 + 1 / 30).depth_m)
    reseeded = cam.with_noise(DepthNoiseConfig(seed=9)).render(world, t=0.5).depth_m
    assert not np.array_equal(a, reseeded)
    other = SimDepthCamera("other", K, look_at([0, 0, 0], [1, 0, 0])).render(world, t=0.5).depth_m
    assert not np.array_equal(a, other)


def test_range_limits_and_decimation() -> None:
    world, cam = _wall_world(0.15)
    assert np.all(cam.with_noise(DepthNoiseConfig.noiseless()).render(world).depth_m == 0)  # < min
    small = SimDepthCamera("cam", K, look_at([0, 0, 0], [1, 0, 0]), NOISELESS, decimation=2)
    assert (small.intrinsics.width, small.intrinsics.height) == (424, 240)
    world, _ = _wall_world(0.8)
    np.testing.assert_allclose(small.ideal_depth(world), 0.8, atol=1e-6)


# ----- configuration and arguments -------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("sigma_base_m", -0.001),
        ("sigma_z2_m_per_m2", 1.0),
        ("quantisation_m", -1.0),
        ("dropout_fraction", 1.5),
        ("grazing_start_deg", 95.0),
        ("flying_pixel_probability", -0.1),
        ("edge_jump_m", 0.0),
        ("seed", -1),
        ("seed", 1.5),
        ("max_depth_m", float("nan")),
    ],
)
def test_bad_config_values_name_the_field(field: str, value: float) -> None:
    with pytest.raises(ConfigError, match=field):
        DepthNoiseConfig(**{field: value})


def test_cross_field_rule_and_overrides() -> None:
    with pytest.raises(ConfigError, match="min_depth_m"):
        DepthNoiseConfig(min_depth_m=1.0, max_depth_m=0.5)
    cfg = DepthNoiseConfig().with_overrides({"sigma_base_m": 0.001})
    assert cfg.sigma_base_m == 0.001
    assert DepthNoiseConfig.from_dict(cfg.to_dict()) == cfg


def test_camera_arguments_are_checked() -> None:
    with pytest.raises(InputError, match="pose_world_camera"):
        SimDepthCamera("cam", K, np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(InputError, match="decimation"):
        SimDepthCamera("cam", K, np.eye(4), decimation=0)
    with pytest.raises(InputError, match="name"):
        SimDepthCamera("", K, np.eye(4))
    with pytest.raises(InputError, match="world"):
        SimDepthCamera("cam", K, np.eye(4)).render("not a world")


# ----- scenes ----------------------------------------------------------------------------------


def test_bench_scenes_and_hip_sampler(scenes) -> None:
    base = ["sphere_head", "ellipsoid_head", "cylinder_arm", "tilted_torso"]
    assert set(scenes) == set(base) | {f"{n}_occluded" for n in base}
    for name in base:
        scene = scenes[name]
        assert [c.name for c in scene.cameras] == ["front", "right45"]
        assert scenes[name + "_occluded"].with_occluder and not scene.with_occluder
        assert scene.occluders([0.0, 0.0, 0.0]) == ()
        for cam in scene.cameras:
            dist = np.linalg.norm(cam.origin_world - scene.world.body(scene.target).bounds()[0])
            assert 0.5 < dist < 1.1
        samples = scene.sample_hips(12, seed=4)
        again = scene.sample_hips(12, seed=4)
        np.testing.assert_array_equal(samples.hips, again.hips)
        cam = scene.camera("front")
        for hip, gt in zip(samples.hips, samples.truths, strict=True):
            assert 0.04 <= gt.distance_m <= 0.11
            assert gt.body == scene.target
            to_cam = cam.origin_world - gt.point
            assert gt.normal @ to_cam / np.linalg.norm(to_cam) >= math.cos(math.radians(50)) - 1e-9
            np.testing.assert_allclose(scene.world.ground_truth(hip).point, gt.point)
    right = scenes["tilted_torso"].sample_hips(5, seed=1, camera="right45")
    assert right.hips.shape == (5, 3)
    with pytest.raises(InputError, match="camera"):
        scenes["sphere_head"].sample_hips(1, camera="left")


def test_demo_scene_has_two_cameras_and_the_parts() -> None:
    demo = demo_scene(decimation=4)
    assert [c.name for c in demo.cameras] == ["front", "right45"]
    parts = {b.part for b in demo.world.bodies}
    assert {"skull_forehead", "face", "chest", "upper_arm", "forearm"} <= parts
    for cam in demo.cameras:
        hits = cam.trace(demo.world)
        seen = {demo.world.surfaces[i].name for i in np.unique(hits.label) if i >= 0}
        assert {"head", "face", "torso", "left_forearm"} <= seen
