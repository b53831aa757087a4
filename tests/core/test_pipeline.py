"""The assembled per-camera pipeline: public API, bad input, degenerate input, invariances."""

from __future__ import annotations

import numpy as np
import pytest
from hapticloud.core.camera import CameraIntrinsics, DepthFrame, look_at
from hapticloud.core.errors import ConfigError
from hapticloud.core.geometry import Box, Capsule, Sphere
from hapticloud.core.perception import CameraPipeline, PerceptionConfig, SurfaceEstimate
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

SETTINGS = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
HIP = np.array([0.0, 0.0, 0.06])
AXIS = np.array([0.0, 0.0, -1.0])


def sphere_cloud(center, radius, hip, n=30000, seed=0, noise=0.0005) -> np.ndarray:
    """Points on the sphere's cap facing the HIP (what a camera behind the HIP sees)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    towards = (hip - center) / np.linalg.norm(hip - center)
    d = d[d @ towards > 0.3]
    return center + d * (radius + noise * rng.normal(size=(len(d), 1)))


def plane_cloud(n=40000, seed=0, half=0.15) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-half, half, size=(n, 2))
    return np.column_stack((xy, 0.0003 * rng.normal(size=n)))


def test_public_api_on_a_sphere_head() -> None:
    center = np.array([0.0, 0.0, -0.09])
    cloud = sphere_cloud(center, 0.09, HIP)
    pipe = CameraPipeline(PerceptionConfig())
    est = pipe.process(cloud, hip=HIP, camera_axis=AXIS, t=1.0)
    assert isinstance(est, SurfaceEstimate) and est.valid
    assert np.linalg.norm(est.centroid - [0.0, 0.0, 0.0]) < 1e-3
    assert est.normal @ [0.0, 0.0, 1.0] > np.cos(np.radians(1.0))
    assert abs(est.d_proj(HIP, 0.04) - 0.02) < 1e-3
    assert set(est.stage_ms) == {"crop", "voxel", "cluster", "rebuild", "abstract", "total"}
    assert est.points is not None and est.points.shape[1] == 3


def test_estimate_constructible_from_the_five_fields() -> None:
    est = SurfaceEstimate(0.5, "front", [0, 0, 1], [0, 0, 2], True)
    assert est.valid and np.allclose(est.normal, [0, 0, 1]) and est.shells == ()


def test_robot_primitives_are_removed_with_a_noise_margin() -> None:
    cloud = plane_cloud()
    # A robot link lying 6 mm above the plane (true radius 5 mm): points measured just outside
    # it (here: on the plane under it) must not reach the shells next to the HIP.
    link = Capsule([-0.02, 0.0, 0.011], [0.02, 0.0, 0.011], 0.005)
    pipe = CameraPipeline(PerceptionConfig())
    est = pipe.process(cloud, HIP, AXIS, exclude=[link])
    assert est.valid
    d = np.linalg.norm(est.points[:, :2] - [0.0, 0.0], axis=1)
    assert not np.any(
        (d < 0.005) & (np.abs(est.points[:, 2]) < 0.002) & (np.abs(est.points[:, 0]) < 0.02)
    )


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"points_world": np.zeros((5, 2))}, "points_world"),
        ({"points_world": np.array([["a", "b", "c"]])}, "points_world"),
        ({"hip": [0.0, 0.0]}, "hip"),
        ({"hip": [0.0, np.nan, 0.0]}, "hip"),
        ({"camera_axis": [0.0, 0.0, 0.0]}, "camera_axis"),
        ({"t": float("nan")}, "t"),
        ({"exclude": ["not a primitive"]}, "exclude"),
    ],
)
def test_bad_arguments_raise_value_error_naming_them(kwargs: dict, name: str) -> None:
    args = {"points_world": plane_cloud(100), "hip": HIP, "camera_axis": AXIS, "t": 0.0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        CameraPipeline().process(**args)


def test_config_cross_check_names_both_fields() -> None:
    with pytest.raises(ConfigError, match=r"^abstraction.r_out_m = 0.3: must not exceed crop"):
        PerceptionConfig().replace_path("abstraction.r_out_m", 0.3)
    # Changed from the other table: the message still names the fields from the top.
    with pytest.raises(ConfigError, match=r"^abstraction.r_out_m = 0.15: must not exceed crop"):
        PerceptionConfig().replace_path("crop.workspace_radius_m", 0.1)


@pytest.mark.parametrize(
    "cloud",
    [
        np.empty((0, 3)),
        np.full((100, 3), np.nan),
        np.array([[0.0, 0.0, 0.0]]),
        np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]]),
        np.tile([[0.0, 0.0, 0.0]], (500, 1)),  # one point, duplicated
        np.column_stack((np.linspace(-0.1, 0.1, 500), np.zeros(500), np.zeros(500))),  # a line
        np.full((50, 3), np.inf),
    ],
    ids=["empty", "all-nan", "one", "two", "duplicates", "collinear", "all-inf"],
)
def test_degenerate_clouds_give_a_flagged_result(cloud: np.ndarray) -> None:
    est = CameraPipeline().process(cloud, HIP, AXIS)
    assert np.all(np.isfinite(est.centroid)) and np.all(np.isfinite(est.normal))
    if not est.valid:
        assert est.reason


def test_nan_rows_are_dropped_not_propagated() -> None:
    cloud = plane_cloud()
    dirty = cloud.copy()
    dirty[::7] = np.nan
    dirty[3::11, 1] = np.inf
    est = CameraPipeline().process(dirty, HIP, AXIS)
    assert est.valid and abs(est.d_proj(HIP, 0.04) - 0.02) < 1e-3


@SETTINGS
@given(
    offset=arrays(np.float64, 3, elements=st.floats(-1e3, 1e3)),
    seed=st.integers(0, 2**16),
)
def test_result_translates_with_the_input(offset: np.ndarray, seed: int) -> None:
    center = np.array([0.0, 0.0, -0.09])
    cloud = sphere_cloud(center, 0.09, HIP, n=8000, seed=seed, noise=0.0)
    near = CameraPipeline().process(cloud, HIP, AXIS)
    far = CameraPipeline().process(cloud + offset, HIP + offset, AXIS)
    assert near.valid and far.valid
    assert np.linalg.norm((far.centroid - offset) - near.centroid) < 1e-3
    assert far.normal @ near.normal > np.cos(np.radians(0.5))


@SETTINGS
@given(
    cloud=arrays(
        np.float64,
        st.tuples(st.integers(0, 60), st.just(3)),
        elements=st.one_of(
            st.floats(-0.2, 0.2), st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 1e-300])
        ),
    )
)
def test_arbitrary_small_clouds_never_nan_never_raise(cloud: np.ndarray) -> None:
    est = CameraPipeline().process(cloud, HIP, AXIS)
    assert np.all(np.isfinite(est.centroid)) and np.all(np.isfinite(est.normal))
    assert abs(np.linalg.norm(est.normal) - 1.0) < 1e-9


def test_depth_frame_path_matches_the_world_array_path() -> None:
    k = CameraIntrinsics.d435(424, 240)
    pose = look_at([0.0, 0.0, 0.7], [0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    depth = np.full((k.height, k.width), 0.7, dtype=np.float32)  # a wall at z = 0 (world)
    depth[:5] = 0.0
    depth[5:9] = np.nan
    frame = DepthFrame(0.0, "front", depth, k, pose)
    hip = np.array([0.0, 0.0, 0.06])
    a = CameraPipeline().process_depth(frame, hip)
    b = CameraPipeline().process(frame.points_world(), hip, frame.axis_world)
    assert a.valid and b.valid
    assert np.linalg.norm(a.centroid - b.centroid) < 1e-6
    assert abs(a.d_proj(hip, 0.04) - 0.02) < 1e-3


def test_reconfigure_applies_at_the_next_frame_and_keeps_memory_when_unchanged() -> None:
    pipe = CameraPipeline()
    cloud = plane_cloud()
    pipe.process(cloud, HIP, AXIS)
    memory = pipe._memory
    pipe.configure(pipe.config.replace_path("voxel.voxel_size_m", 0.005))
    assert pipe._memory is memory
    pipe.configure(pipe.config.replace_path("reconstruction.r_in_m", 0.03))
    assert pipe._memory is not memory
    with pytest.raises(ValueError, match="config"):
        pipe.configure("nope")  # type: ignore[arg-type]


def test_primitives_validate_their_arguments() -> None:
    with pytest.raises(ValueError, match="radius"):
        Sphere([0, 0, 0], -1.0)
    with pytest.raises(ValueError, match="half_extents"):
        Box([0, 0, 0], [1, 0, 1])
    with pytest.raises(ValueError, match="rotation"):
        Box([0, 0, 0], [1, 1, 1], rotation=np.diag([1.0, 1.0, -1.0]))


def test_points_of_rejected_clusters_are_handed_on() -> None:
    """A small blob beside the surface is a cluster stage C drops: the estimate carries it."""
    center = np.array([0.0, 0.0, -0.09])
    rng = np.random.default_rng(3)
    blob = np.array([0.06, 0.06, 0.02]) + 0.002 * rng.normal(size=(40, 3))
    cloud = np.vstack([sphere_cloud(center, 0.09, HIP), blob])
    est = CameraPipeline(PerceptionConfig()).process(cloud, HIP, AXIS)
    assert est.valid and est.rejected is not None and est.rejected.shape[1] == 3
    assert est.rejected.shape[0] > 0 and not est.rejected.flags.writeable
    assert np.linalg.norm(est.rejected.mean(axis=0) - [0.06, 0.06, 0.02]) < 0.01


def _cut_sphere(hip: np.ndarray, cut_m: float) -> np.ndarray:
    """A sphere head under the HIP with the side x < cut_m removed (the end effector hides the
    closest point, and the points lie on one side of it: extrapolated, not surrounded)."""
    cloud = sphere_cloud(np.array([0.0, 0.0, -0.09]), 0.09, hip, seed=2)
    return cloud[cloud[:, 0] > cut_m]


@pytest.mark.parametrize("cut_m", [0.014, 0.022])
def test_an_extrapolated_fit_is_moved_toward_the_hip_by_its_own_standard_error(cut_m) -> None:
    def d_proj(sigmas: float, cloud: np.ndarray) -> float:
        # No linear margin: sigmas 0 reports the fit as it is.
        cfg = PerceptionConfig(extrapolation_sigmas=sigmas, extrapolation_margin=0.0)
        est = CameraPipeline(cfg).process(cloud, hip=HIP, camera_axis=AXIS, t=1.0)
        assert est.valid, est.reason
        return est.d_proj(HIP, 0.04)

    cut = _cut_sphere(HIP, cut_m)
    plain, four, eight = (d_proj(s, cut) for s in (0.0, 4.0, 8.0))
    true = 0.06 - 0.04
    assert abs(plain - true) < 0.5e-3  # a sphere is a quadric: extrapolated, still exact
    shift = plain - four
    assert 0.1e-3 < shift < 3e-3  # toward the HIP: what is not seen is taken as nearer
    assert plain - eight == pytest.approx(2 * shift, rel=1e-6)  # in standard errors
    # Supported by its points: taken as it is, whatever the setting.
    whole = sphere_cloud(np.array([0.0, 0.0, -0.09]), 0.09, HIP, seed=2)
    assert d_proj(0.0, whole) == d_proj(8.0, whole)
    # The default (extrapolation_sigmas 0) moves it by the linear margin instead: nearer too.
    est = CameraPipeline(PerceptionConfig()).process(cut, hip=HIP, camera_axis=AXIS, t=1.0)
    assert est.valid and est.d_proj(HIP, 0.04) < plain


def test_a_wider_hole_leaves_a_larger_standard_error() -> None:
    shifts = []
    for cut_m in (0.012, 0.024):
        d = [
            CameraPipeline(PerceptionConfig(extrapolation_sigmas=s, extrapolation_margin=0.0))
            .process(_cut_sphere(HIP, cut_m), hip=HIP, camera_axis=AXIS, t=1.0)
            .d_proj(HIP, 0.04)
            for s in (0.0, 1.0)
        ]
        shifts.append(d[0] - d[1])
    assert 0.0 < shifts[0] < shifts[1]
