"""Region-of-interest renders of the simulated D435 and its per-pixel (counter-based) noise.

A ROI render must be the full render, bit for bit, inside the ROI (and 0 outside), so that the
perception sees exactly what it would have seen; the noise must keep the D435-like statistics.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hapticloud.core.camera import CameraIntrinsics, look_at
from hapticloud.core.errors import InputError
from hapticloud.core.geometry import Box, Capsule, Sphere
from hapticloud.core.perception import CameraPipeline
from hapticloud.core.perception.crop import CropConfig, crop_depth_frame
from hapticloud.core.scene import load_scene
from hapticloud.core.sim import raycast
from hapticloud.core.sim.bodies import BoxBody, SphereBody
from hapticloud.core.sim.closed_loop import ClosedLoopSim, camera_pose
from hapticloud.core.sim.depth_camera import (
    EMPTY_ROI,
    OCCLUDER,
    ROI_MARGIN_PX,
    DepthNoiseConfig,
    SimDepthCamera,
)
from hapticloud.core.sim.exo import solve_hip_ik
from hapticloud.core.sim.noise import (
    NOISE_MARGIN_PX,
    apply_depth_noise,
    frame_key,
    pixel_bits,
)
from hapticloud.core.sim.scenes import perception_bench_scenes
from hapticloud.core.sim.world import SimWorld

K = CameraIntrinsics.d435()


def _bits(a: np.ndarray) -> np.ndarray:
    """float32 images compared by their bits (0.0 and -0.0, NaN payloads differ)."""
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


def _cams(sim: ClosedLoopSim, decimation: int) -> list[SimDepthCamera]:
    """The scene's cameras at ``decimation``, built as the closed loop builds them."""
    out = []
    for cam in sim.cameras:
        spec = cam.spec
        intr = CameraIntrinsics.d435(spec.width_px, spec.height_px, spec.hfov_deg)
        pose = camera_pose(spec, sim.hip0)
        out.append(SimDepthCamera(spec.name, intr, pose, spec.noise, decimation=decimation))
    return out


def _track(sim: ClosedLoopSim, times: list[float]) -> list[tuple[float, np.ndarray, tuple]]:
    """``(t, HIP, robot capsules)`` along the scene's scripted hand, the robot by IK."""
    out = []
    q = sim.q0
    for t in times:
        hip = sim.patient.intent.position(t) if sim.patient is not None else sim.hip0
        q, _ = solve_hip_ik(sim.robot, hip, q)
        out.append((t, np.asarray(hip), tuple(sim.robot.link_capsules(q))))
    return out


@pytest.fixture(scope="module")
def demo() -> ClosedLoopSim:
    return ClosedLoopSim(load_scene("demo"))


@pytest.fixture(scope="module")
def moving() -> ClosedLoopSim:
    return ClosedLoopSim(load_scene("moving-surface"))


def _assert_roi_render_is_full_render(
    full_cam: SimDepthCamera,
    roi_cam: SimDepthCamera,
    world: SimWorld,
    t: float,
    occluders: tuple,
    roi: tuple[int, int, int, int],
) -> None:
    full = full_cam.render(world, t, occluders).depth_m
    part = roi_cam.render(world, t, occluders, roi=roi).depth_m
    r0, r1, c0, c1 = roi
    assert part.shape == full.shape and part.dtype == np.float32
    np.testing.assert_array_equal(_bits(part[r0:r1, c0:c1]), _bits(full[r0:r1, c0:c1]))
    inside = np.zeros(part.shape, dtype=bool)
    inside[r0:r1, c0:c1] = True
    assert not np.any(part[~inside])  # 0 (invalid) outside


# ----- equivalence: ROI render == full render inside the ROI --------------------------------------


@pytest.mark.parametrize("decimation", [1, 2])
@pytest.mark.parametrize("shared", [False, True], ids=["own-caches", "shared-caches"])
def test_roi_render_equals_full_render_with_the_robot_in_view(
    demo: ClosedLoopSim, decimation: int, shared: bool
) -> None:
    """Several HIPs/frames of the demo's reach, both cameras, robot link capsules as occluders.

    ``shared``: the ROI render reuses the full render's ray casts (a static group sliced);
    otherwise it casts on its own (first a part, then the static room once whole).
    """
    crop = demo.scene.config.perception.crop
    full_cams = _cams(demo, decimation)
    roi_cams = full_cams if shared else _cams(demo, decimation)
    robot_seen = 0
    for full_cam, roi_cam in zip(full_cams, roi_cams, strict=True):
        for t, hip, capsules in _track(demo, [0.0, 0.7, 1.2, 1.9, 2.5, 3.4]):
            world = demo.world.at(t)
            roi = roi_cam.workspace_roi(hip, crop)
            assert roi != EMPTY_ROI
            _assert_roi_render_is_full_render(full_cam, roi_cam, world, t, capsules, roi)
            hits = roi_cam.trace(world, t, capsules, roi=roi)
            robot_seen += int(np.count_nonzero(hits.label == OCCLUDER))
    assert robot_seen > 1000  # the robot's links really are in the ROIs


@pytest.mark.parametrize("decimation", [1, 2])
def test_roi_render_equals_full_render_with_a_moving_body(
    moving: ClosedLoopSim, decimation: int
) -> None:
    """The rising plate changes its ray-cast shift every frame: the per-part cast path."""
    crop = moving.scene.config.perception.crop
    full_cams, roi_cams = _cams(moving, decimation), _cams(moving, decimation)
    times = [0.05 + k / 30 for k in range(6)]
    for full_cam, roi_cam in zip(full_cams, roi_cams, strict=True):
        for t, hip, capsules in _track(moving, times):
            world = moving.world.at(t)
            roi = roi_cam.workspace_roi(hip, crop)
            _assert_roi_render_is_full_render(full_cam, roi_cam, world, t, capsules, roi)


def test_roi_touching_the_image_border_and_odd_rois(demo: ClosedLoopSim) -> None:
    crop = demo.scene.config.perception.crop
    full_cam, roi_cam = _cams(demo, 2)[0], _cams(demo, 2)[0]
    k = full_cam.intrinsics
    t, _, capsules = _track(demo, [1.2])[0]
    world = demo.world.at(t)
    # A HIP 0.8 m out along the ray of a corner pixel: its ROI is clipped by two image edges.
    corners = [(1.0, 1.0, True), (k.width - 2.0, k.height - 2.0, True), (1.0, k.height / 2, False)]
    for u, v, corner in corners:
        ray = np.array([(u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0])
        pose = full_cam.pose_world_camera
        hip = pose[:3, 3] + 0.8 * pose[:3, :3] @ ray
        roi = roi_cam.workspace_roi(hip, crop)
        rows_clipped = roi[0] == 0 or roi[1] == k.height
        cols_clipped = roi[2] == 0 or roi[3] == k.width
        assert cols_clipped and (rows_clipped or not corner)
        _assert_roi_render_is_full_render(full_cam, roi_cam, world, t, capsules, roi)
    for roi in [
        (0, k.height, 0, k.width),  # the whole image
        (0, 1, 0, 1),  # one corner pixel
        (k.height - 7, k.height, 0, k.width),  # a strip along the bottom edge
        (50, 51, 10, k.width - 10),  # one row
        (3, 200, k.width - 1, k.width),  # one column at the right edge
    ]:
        _assert_roi_render_is_full_render(full_cam, roi_cam, world, t, capsules, roi)


def test_roi_render_with_spheres_boxes_and_flying_pixels() -> None:
    """The general closed forms (sphere, box) beside the capsules; every pixel may fly."""
    scene = perception_bench_scenes()["sphere_head_occluded"]
    noise = DepthNoiseConfig(flying_pixel_probability=1.0, dropout_fraction=0.1, seed=5)
    cam = scene.cameras[0].with_noise(noise)
    other = scene.cameras[0].with_noise(noise)
    crop = CropConfig(workspace_radius_m=0.2)
    for i, hip in enumerate(scene.sample_hips(4, seed=3).hips):
        occ = (
            *scene.occluders(hip),
            Box(center=hip + np.array([0.0, 0.05, 0.1]), half_extents=[0.02, 0.03, 0.04]),
            Sphere(center=hip + np.array([0.0, -0.06, 0.0]), radius=0.02),
        )
        roi = other.workspace_roi(hip, crop)
        _assert_roi_render_is_full_render(cam, other, scene.world, i / 30, occ, roi)


def test_empty_roi_renders_nothing_and_bad_rois_are_refused(demo: ClosedLoopSim) -> None:
    cam = _cams(demo, 2)[0]
    world = demo.world.at(0.0)
    behind = cam.origin_world - 1.0 * cam.axis_world
    assert cam.workspace_roi(behind) == EMPTY_ROI
    frame = cam.render(world, 0.0, roi=EMPTY_ROI)
    assert frame.depth_m.shape == (cam.intrinsics.height, cam.intrinsics.width)
    assert not frame.depth_m.any()
    h, w = cam.intrinsics.height, cam.intrinsics.width
    for bad in [(0, 10, 5), (-1, 10, 0, 10), (0, h + 1, 0, 10), (5, 3, 0, 10), (0.5, 2, 0, 3)]:
        with pytest.raises(InputError, match="roi"):
            cam.render(world, 0.0, roi=bad)
    with pytest.raises(InputError, match="margin_px"):
        cam.workspace_roi(demo.hip0, margin_px=-1)
    with pytest.raises(InputError, match="world"):
        cam.render("not a world", 0.0, roi=EMPTY_ROI)
    assert cam.render(world, 0.0, roi=np.array([1, 5, 2, 9])).depth_m.shape == (h, w)


# ----- the ROI is what the crop reads -------------------------------------------------------------


@pytest.mark.parametrize("decimation", [1, 2, 4])
def test_workspace_roi_holds_the_crop_region(demo: ClosedLoopSim, decimation: int) -> None:
    rng = np.random.default_rng(4)
    crop = demo.scene.config.perception.crop
    for cam in _cams(demo, decimation):
        k = cam.intrinsics
        for _ in range(40):
            hip = demo.hip0 + rng.uniform(-0.4, 0.4, 3)
            frame = cam.render(demo.world.at(0.0), 0.0, roi=EMPTY_ROI)  # geometry only
            region = crop_depth_frame(frame, hip, (), crop).region
            roi = cam.workspace_roi(hip, crop)
            if region is None:
                assert roi == EMPTY_ROI
                continue
            m = ROI_MARGIN_PX
            grown = (
                max(0, region[0] - m),
                min(k.height, region[1] + m),
                max(0, region[2] - m),
                min(k.width, region[3] + m),
            )
            assert roi == grown


def test_perception_on_roi_frames_equals_full_frames(demo: ClosedLoopSim) -> None:
    """Same estimates, bit for bit, frame after frame (the pipelines keep a memory)."""
    config = demo.scene.config.perception
    for cam in _cams(demo, 2):
        full_pipe = CameraPipeline(config, camera=cam.name)
        roi_pipe = CameraPipeline(config, camera=cam.name)
        n_valid = 0
        for t, hip, capsules in _track(demo, [k / 30 for k in range(0, 120, 6)]):
            world = demo.world.at(t)
            full = full_pipe.process_depth(cam.render(world, t, capsules), hip, capsules)
            roi = cam.workspace_roi(hip, config.crop)
            part = roi_pipe.process_depth(cam.render(world, t, capsules, roi=roi), hip, capsules)
            assert (part.valid, part.reason, part.free_m) == (full.valid, full.reason, full.free_m)
            np.testing.assert_array_equal(part.centroid, full.centroid)
            np.testing.assert_array_equal(part.normal, full.normal)
            assert part.quality == full.quality and part.n_points == full.n_points
            n_valid += full.valid
        assert n_valid > 5


def test_closed_loop_capture_sees_what_a_full_render_shows() -> None:
    """``Assembly.capture`` (ROI render) gives the estimate a full frame gives."""
    sim = ClosedLoopSim(load_scene("demo"))
    config = sim.scene.config.perception
    for cam in sim.cameras:
        pipe = CameraPipeline(config, camera=cam.spec.name)
        q = sim.q0
        for t in [0.0, 0.5, 1.0, 1.5, 2.0]:
            hip = np.asarray(sim.patient.intent.position(t))
            q, _ = solve_hip_ik(sim.robot, hip, q)
            got = sim.parts.capture(cam, t, q, hip, sim.rng)
            capsules = sim.robot.link_capsules(q)
            frame = cam.camera.render(sim.world.at(t), t, occluders=capsules)
            want = pipe.process_depth(frame, hip, exclude=capsules)
            assert (got.valid, got.reason) == (want.valid, want.reason)
            np.testing.assert_array_equal(got.centroid, want.centroid)
            np.testing.assert_array_equal(got.normal, want.normal)


# ----- the noise: part == whole, per pixel --------------------------------------------------------


def test_noise_of_a_part_is_the_noise_of_the_whole() -> None:
    """Directly on a synthetic ideal image with many depth edges and invalid pixels."""
    rng = np.random.default_rng(0)
    h, w = 90, 130
    ideal = np.repeat(np.repeat(rng.uniform(0.3, 3.0, (9, 13)), 10, 0), 10, 1).astype(np.float32)
    ideal[rng.random((h, w)) < 0.05] = 0.0
    ideal[rng.random((h, w)) < 0.01] = np.inf
    cos = rng.uniform(0.0, 1.0, (h, w)).astype(np.float32)
    cfg = DepthNoiseConfig(flying_pixel_probability=0.5, dropout_fraction=0.05, seed=11)
    key = frame_key(cfg.seed, "cam", 0.25)
    whole = apply_depth_noise(ideal, cfg, key, cos)
    m = NOISE_MARGIN_PX
    for r0, r1, c0, c1 in [(0, h, 0, w), (0, 10, 0, 10), (37, 61, 5, 129), (80, 90, 120, 130)]:
        p0, p1 = max(0, r0 - m), min(h, r1 + m)
        q0, q1 = max(0, c0 - m), min(w, c1 + m)
        part = apply_depth_noise(
            ideal[p0:p1, q0:q1], cfg, key, cos[p0:p1, q0:q1], origin=(p0, q0), image_width=w
        )
        inner = part[r0 - p0 : r1 - p0, c0 - q0 : c1 - q0]
        np.testing.assert_array_equal(_bits(inner), _bits(whole[r0:r1, c0:c1]))
    with pytest.raises(InputError, match="origin"):
        apply_depth_noise(ideal[:, :20], cfg, key, origin=(0, 120), image_width=w)


def _splitmix64(state: int) -> int:
    """Reference splitmix64 output function (Steele, Lea, Flood 2014; Vigna's constants)."""
    z = state & (2**64 - 1)
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & (2**64 - 1)
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & (2**64 - 1)
    return z ^ (z >> 31)


def test_noise_key_and_bits_are_pinned() -> None:
    """Regression pin of the counter-based generator (integer arithmetic only: the same on
    every machine). Changing it changes every simulated run's noise: do so on purpose only."""
    assert frame_key(0, "front", 0.5) == 1926184106238813416
    key = frame_key(3, "right45", 1 / 30)
    index = np.array([0, 1, 407039])
    bits = pixel_bits(key, index, 0)
    assert bits.dtype == np.uint64
    assert [hex(int(b)) for b in bits] == [
        "0x9aeb25216c0fe188",
        "0x31c251be18b97171",
        "0x1e3f93f5d595ad9f",
    ]
    # It is splitmix64 seeded with the key, at counter 3 * pixel + draw.
    for draw in range(3):
        want = [_splitmix64(key + (3 * int(i) + draw) * 0x9E3779B97F4A7C15) for i in index]
        assert [int(b) for b in pixel_bits(key, index, draw)] == want


def test_uniform_bits_look_uniform() -> None:
    key = frame_key(0, "cam", 0.0)
    bits = pixel_bits(key, np.arange(1 << 20), 1)
    top = (bits >> np.uint64(56)).astype(np.int64)  # 256 bins
    counts = np.bincount(top, minlength=256)
    expected = bits.size / 256
    chi2 = float(np.sum((counts - expected) ** 2 / expected))
    assert chi2 < 255 + 5 * math.sqrt(2 * 255)  # ~5 sigma of the chi-square with 255 dof
    low = (bits & np.uint64(0xFF)).astype(np.int64)
    chi2_low = float(np.sum((np.bincount(low, minlength=256) - expected) ** 2 / expected))
    assert chi2_low < 255 + 5 * math.sqrt(2 * 255)


# ----- the noise: D435-like statistics ------------------------------------------------------------


def _wall(z: float, name: str = "cam") -> tuple[SimWorld, SimDepthCamera]:
    """A wall facing a camera at the origin looking along +x, its face at depth ``z``."""
    wall = BoxBody(
        name="wall", part="background", center=[z + 0.05, 0, 0], half_extents_m=[0.05, 5, 5]
    )
    dummy = SphereBody(name="far", part="chest", center=[-5.0, 0, 0], radius_m=0.1)
    return SimWorld([dummy], [wall]), SimDepthCamera(name, K, look_at([0, 0, 0], [1, 0, 0]))


GAUSSIAN_ONLY = DepthNoiseConfig(
    quantisation_m=0.0, dropout_fraction=0.0, grazing_dropout=0.0, flying_pixel_probability=0.0
)


@pytest.mark.parametrize("z", [0.4, 1.0, 2.0, 3.5])
def test_depth_error_is_gaussian_with_sigma_of_z(z: float) -> None:
    world, cam = _wall(z)
    err = cam.with_noise(GAUSSIAN_ONLY).render(world, t=0.1).depth_m.astype(np.float64) - z
    sigma = GAUSSIAN_ONLY.sigma_m(z)
    assert err.size == K.width * K.height
    n = err / sigma
    assert abs(n.std() - 1.0) < 0.01  # 407k samples: the std's own error is ~0.1 %
    assert abs(n.mean()) < 0.01
    for k, p in [(1, 0.682689), (2, 0.954500), (3, 0.997300)]:
        assert np.mean(np.abs(n) < k) == pytest.approx(p, abs=0.004)
    kurtosis = float(np.mean(n**4) / np.mean(n**2) ** 2)
    assert kurtosis == pytest.approx(3.0, abs=0.06)


def test_noise_is_independent_between_pixels_frames_and_cameras() -> None:
    world, cam = _wall(1.0)
    cam = cam.with_noise(GAUSSIAN_ONLY)
    a = cam.render(world, t=0.5).depth_m.astype(np.float64) - 1.0
    b = cam.render(world, t=0.5 + 1 / 30).depth_m.astype(np.float64) - 1.0
    _, other = _wall(1.0, "other")
    c = other.with_noise(GAUSSIAN_ONLY).render(world, t=0.5).depth_m.astype(np.float64) - 1.0

    def corr(x: np.ndarray, y: np.ndarray) -> float:
        return float(np.corrcoef(x.ravel(), y.ravel())[0, 1])

    limit = 5 / math.sqrt(a.size)  # 5 sigma of a correlation estimate
    assert abs(corr(a[:, 1:], a[:, :-1])) < limit  # horizontal neighbours
    assert abs(corr(a[1:], a[:-1])) < limit  # vertical neighbours
    assert abs(corr(a, b)) < limit  # next frame
    assert abs(corr(a, c)) < limit  # another camera


@pytest.mark.parametrize("p", [0.02, 0.1, 0.3])
def test_dropout_fraction(p: float) -> None:
    world, cam = _wall(0.8)
    cfg = DepthNoiseConfig(dropout_fraction=p, grazing_dropout=0.0, seed=2)
    depth = cam.with_noise(cfg).render(world).depth_m
    tol = 5 * math.sqrt(p * (1 - p) / depth.size)
    assert (depth == 0).mean() == pytest.approx(p, abs=tol)


def test_grazing_dropouts_follow_the_ramp() -> None:
    wall = BoxBody(name="wall", part="background", center=[1.0, 0, 0], half_extents_m=[3, 3, 0.05])
    far = SphereBody(name="far", part="chest", center=[-5, 0, 0], radius_m=0.1)
    world = SimWorld([far], [wall])
    eye = np.array([1.0, 0.0, 0.25])
    down = np.array([math.cos(math.radians(20)), 0.0, -math.sin(math.radians(20))])
    cam = SimDepthCamera("cam", K, look_at(eye, eye + down))
    cfg = DepthNoiseConfig.noiseless(
        dropout_fraction=0.02, grazing_dropout=0.5, grazing_start_deg=65.0
    )
    hits = cam.trace(world, incidence=True)
    seen = (hits.label >= 0) & (hits.depth_m > cfg.min_depth_m) & (hits.depth_m < cfg.max_depth_m)
    cos_start = math.cos(math.radians(65.0))
    ramp = np.clip((cos_start - hits.cos_incidence[seen]) / cos_start, 0.0, 1.0)
    p = 0.02 + 0.5 * ramp
    assert (ramp > 0.5).sum() > 10000
    dropped = cam.with_noise(cfg).render(world).depth_m[seen] == 0
    expected, sd = float(p.sum()), math.sqrt(float((p * (1 - p)).sum()))
    assert abs(float(dropped.sum()) - expected) < 5 * sd
    steep = ramp > 0.8
    assert dropped[steep].mean() == pytest.approx(p[steep].mean(), abs=0.02)


def test_flying_pixels_fly_with_their_probability_uniformly_between_extremes() -> None:
    ball = SphereBody(name="ball", part="skull_forehead", center=[0.5, 0, 0], radius_m=0.15)
    wall = BoxBody(name="wall", part="background", center=[1.55, 0, 0], half_extents_m=[0.05, 5, 5])
    world = SimWorld([ball], [wall])
    cam = SimDepthCamera("cam", K, look_at([0, 0, 0], [1, 0, 0]))
    ideal = cam.with_noise(DepthNoiseConfig.noiseless()).ideal_depth(world)
    cfg = DepthNoiseConfig.noiseless(flying_pixel_probability=0.3)
    flying = cam.with_noise(cfg).render(world).depth_m
    lo, hi = ideal.copy(), ideal.copy()
    for axis in (0, 1):
        for shift in (1, -1):
            nb = np.roll(ideal, shift, axis=axis)
            inside = np.ones_like(ideal, dtype=bool)  # np.roll wraps: keep inner pixels only
            if axis == 0:
                inside[0 if shift == 1 else -1, :] = False
            else:
                inside[:, 0 if shift == 1 else -1] = False
            lo = np.where(inside, np.minimum(lo, nb), lo)
            hi = np.where(inside, np.maximum(hi, nb), hi)
    edge = (ideal > 0) & (hi - lo > cfg.edge_jump_m)
    edge[[0, -1], :] = edge[:, [0, -1]] = False
    changed = flying != ideal
    assert not np.any(changed & ~edge)
    n_edge = int(edge.sum())
    assert n_edge > 1000
    assert changed[edge].mean() == pytest.approx(0.3, abs=5 * math.sqrt(0.21 / n_edge))
    where = (flying[changed] - lo[changed]) / (hi[changed] - lo[changed])
    assert np.all((where >= 0) & (where <= 1))
    assert where.mean() == pytest.approx(0.5, abs=0.04)


# ----- the closed forms the ROI relies on ---------------------------------------------------------


def test_a_rays_hit_does_not_depend_on_the_rays_cast_with_it() -> None:
    """Row by row arithmetic: one ray alone gets the bits it gets among 10k others."""
    rng = np.random.default_rng(1)
    origin = np.array([0.9, -0.2, 1.4])
    target = rng.normal([0.0, 0.1, 1.1], 0.08, (10_000, 3))
    dirs = target - origin
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rot *= np.sign(np.linalg.det(rot))
    cases = [
        lambda o, d: raycast.ray_capsule(o, d, [0, 0.1, 1.0], [0.05, 0.15, 1.2], 0.05),
        lambda o, d: raycast.ray_ellipsoid(o, d, [0, 0.1, 1.1], [0.1, 0.07, 0.12], rot),
        lambda o, d: raycast.ray_box(o, d, [0, 0.1, 1.1], [0.05, 0.08, 0.1], rot),
        lambda o, d: raycast.ray_cylinder(o, d, [0, 0.1, 1.0], [0.05, 0.15, 1.2], 0.05),
        lambda o, d: raycast.ray_sphere(o, d, [0, 0.1, 1.1], 0.09),
    ]
    for cast in cases:
        t_all, n_all = cast(origin, dirs)
        assert np.isfinite(t_all).sum() > 100
        for i in [0, 1, 4097, 9_999, *np.flatnonzero(np.isfinite(t_all))[:50]]:
            t_one, n_one = cast(origin, dirs[i : i + 1])
            assert t_one.tobytes() == t_all[i : i + 1].tobytes()
            assert n_one.tobytes() == n_all[i : i + 1].tobytes()


def test_lean_capsule_depths_match_the_general_closed_form() -> None:
    rng = np.random.default_rng(2)
    origin = np.array([0.8, 0.3, 1.5])
    for _ in range(20):
        a = rng.normal([0.0, 0.0, 1.0], 0.2)
        b = a + rng.normal(0.0, 0.15, 3) * rng.integers(0, 2)  # some of zero length
        r = float(rng.uniform(0.01, 0.08))
        dirs = rng.normal(0.5 * (a + b), 0.15, (4000, 3)) - origin
        dirs *= rng.uniform(0.2, 3.0, (4000, 1))  # any length: t is in its units
        t_ref, n_ref = raycast.ray_capsule(origin, dirs, a, b, r)
        dd = np.sum(dirs * dirs, axis=1)
        t = raycast.capsule_depths((dirs[:, 0], dirs[:, 1], dirs[:, 2]), dd, origin, a, b, r)
        both = np.isfinite(t) & np.isfinite(t_ref)
        # Hit or miss may differ only for rays grazing the surface (rounding).
        assert np.count_nonzero(np.isfinite(t) != np.isfinite(t_ref)) <= 2
        np.testing.assert_allclose(t[both], t_ref[both], rtol=1e-9)
        points = origin + t[both, None] * dirs[both]
        n = raycast.capsule_normals(
            points,
            np.broadcast_to(a, points.shape),
            np.broadcast_to(b, points.shape),
            np.full(len(points), r),
        )
        np.testing.assert_allclose(n, n_ref[both], atol=1e-7)
    # A ray from beyond an end along the axis meets the end ball only.
    a, b = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.2])
    d = np.array([[0.0, 0.0, -1.0]])
    o = np.array([0.0, 0.0, 2.0])
    t = raycast.capsule_depths((d[:, 0], d[:, 1], d[:, 2]), np.ones(1), o, a, b, 0.05)
    assert t[0] == pytest.approx(0.75)


def test_capsules_holding_the_camera_take_the_general_form() -> None:
    """A link around the camera hides everything behind it (general closed form: the exit)."""
    world, cam = _wall(1.0)
    cam = cam.with_noise(DepthNoiseConfig.noiseless())
    around = Capsule(a=[-0.1, 0.0, 0.0], b=[0.1, 0.0, 0.0], radius=0.3)
    hits = cam.trace(world, occluders=(around,), roi=(200, 260, 400, 450))
    assert np.all(hits.label == OCCLUDER)
    full = cam.trace(world, occluders=(around,))
    np.testing.assert_array_equal(hits.depth_m, full.depth_m[200:260, 400:450])


def test_closed_loop_renders_the_roi_unless_a_recorder_takes_the_frames() -> None:
    """A recorder (``frame_sink``) may store more than the crop reads: it gets whole frames."""
    sim = ClosedLoopSim(load_scene("demo"))
    cam = sim.cameras[0]
    asked: list[object] = []
    render = cam.camera.render

    def spy(*args: object, **kwargs: object) -> object:
        asked.append(kwargs.get("roi"))
        return render(*args, **kwargs)

    cam.camera.render = spy  # type: ignore[method-assign]
    sim.parts.capture(cam, 0.0, sim.q0, sim.hip0, sim.rng)
    roi = cam.camera.workspace_roi(sim.hip0, sim.scene.config.perception.crop)
    assert asked == [roi] and roi != EMPTY_ROI
    stored: list[tuple] = []
    sim.parts.capture(
        cam, 1 / 30, sim.q0, sim.hip0, sim.rng, frame_sink=lambda *frame: stored.append(frame)
    )
    assert asked[-1] is None
    depth = stored[-1][0].depth_m
    outside = np.ones(depth.shape, dtype=bool)
    outside[roi[0] : roi[1], roi[2] : roi[3]] = False
    assert np.count_nonzero(depth[outside]) > 0.5 * outside.sum()  # the room, all around
