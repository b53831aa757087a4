"""Stage E: configuration, the paper's shells, the nearest-point baseline and the entry point."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hapticloud.core.errors import ConfigError, InputError
from hapticloud.core.perception.abstraction import (
    METHODS,
    AbstractionConfig,
    SurfaceFit,
    estimate_surface,
    shell_edges,
)
from hapticloud.core.perception.nearest import nearest_point
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from synthetic_patches import make_patch

SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
CAM = np.array([0.0, 0.0, -1.0])  # looking down at the plane z = 0 from above
HIP = np.array([0.01, -0.02, 0.06])
FAR = np.array([1e3, -1e3, 1e3])


def _cfg(method: str, **kw) -> AbstractionConfig:
    return dataclasses.replace(AbstractionConfig(), method=method, **kw)


def _grid_plane(step=0.004, half=0.15, z=0.0):
    g = np.arange(-half, half + 1e-9, step)
    x, y = np.meshgrid(g, g)
    return np.column_stack((x.ravel(), y.ravel(), np.full(x.size, z)))


def _assert_finite(fit: SurfaceFit) -> None:
    assert np.all(np.isfinite(fit.centroid)) and np.all(np.isfinite(fit.normal))
    assert np.linalg.norm(fit.normal) == pytest.approx(1.0)
    assert 0.0 <= fit.quality <= 1.0
    for shell in fit.shells:
        assert np.all(np.isfinite(shell.center)) and np.all(np.isfinite(shell.normal))


# ----- configuration -----------------------------------------------------------------------------


def test_config_defaults_validate_and_round_trip():
    cfg = AbstractionConfig()
    assert cfg.method == "quadric"
    assert AbstractionConfig.from_dict(cfg.to_dict()) == cfg
    assert cfg.replace_path("quadric.bandwidth_m", 0.03).quadric.bandwidth_m == 0.03


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"r_in_m": 0.2, "r_out_m": 0.15}, "r_in_m"),
        ({"r_in_m": 0.15, "r_out_m": 0.15}, "r_in_m"),
        ({"method": "mls"}, "method"),
        ({"reject_fraction": 0.95}, "reject_fraction"),
        ({"n_shells": 0}, "n_shells"),
        ({"quadric": {"bandwidth_m": -1.0}}, "bandwidth_m"),
        ({"quadric": {"model": "cubic"}}, "model"),
    ],
)
def test_config_errors_name_the_field(overrides, field):
    with pytest.raises(ConfigError, match=field):
        AbstractionConfig.from_dict(overrides)


# ----- entry point: arguments and degenerate inputs ----------------------------------------------


@pytest.mark.parametrize("method", METHODS)
def test_wrong_shapes_raise_value_errors_naming_the_argument(method):
    cfg = _cfg(method)
    pts = _grid_plane()
    with pytest.raises(ValueError, match="points_world"):
        estimate_surface(pts[:, :2], HIP, CAM, cfg)
    with pytest.raises(ValueError, match="points_world"):
        estimate_surface(pts.astype(str), HIP, CAM, cfg)
    with pytest.raises(ValueError, match="hip"):
        estimate_surface(pts, HIP[:2], CAM, cfg)
    with pytest.raises(InputError, match="hip"):
        estimate_surface(pts, [np.nan, 0, 0], CAM, cfg)
    with pytest.raises(ValueError, match="camera_axis"):
        estimate_surface(pts, HIP, [0, 0, 0], cfg)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(
    "points",
    [
        np.empty((0, 3)),
        np.full((50, 3), np.nan),
        [[0.0, 0.0, 0.0]],
        [[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]],
        np.outer(np.linspace(-0.1, 0.1, 60), [1.0, 0.5, 0.0]),  # collinear
        np.tile([[0.0, 0.0, 0.0]], (40, 1)),  # one point, duplicated
        np.tile([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]], (20, 1)),
        [[5.0, 5.0, 5.0]] * 10,  # all beyond r_out
    ],
)
def test_degenerate_inputs_give_flagged_or_finite_results(method, points):
    fit = estimate_surface(points, HIP, CAM, _cfg(method))
    _assert_finite(fit)
    if not fit.valid:
        assert fit.reason


@pytest.mark.parametrize("method", METHODS)
def test_flat_surface_is_found_exactly_by_every_method(method):
    pts = _grid_plane()
    fit = estimate_surface(pts, HIP, CAM, _cfg(method))
    assert fit.valid, fit.reason
    assert np.allclose(fit.normal, [0, 0, 1], atol=1e-9)
    assert abs(fit.centroid[2]) < 1e-9
    assert fit.d_proj(HIP, 0.04) == pytest.approx(0.02, abs=1e-9)
    if method != "nearest":  # the baseline reports a grid point, not the foot of the HIP
        assert np.allclose(fit.centroid[:2], HIP[:2], atol=2e-3)


@pytest.mark.parametrize("method", METHODS)
def test_duplicated_points_give_the_same_answer(method):
    pts = _grid_plane(step=0.006)
    one = estimate_surface(pts, HIP, CAM, _cfg(method))
    two = estimate_surface(np.vstack((pts, pts)), HIP, CAM, _cfg(method))
    assert one.valid and two.valid
    assert np.allclose(one.centroid, two.centroid, atol=1e-6)
    assert np.allclose(one.normal, two.normal, atol=1e-6)


@pytest.mark.parametrize("method", METHODS)
def test_results_translate_with_the_input(method):
    rng = np.random.default_rng(11)
    patch = make_patch("sphere", rng, hole_radius_m=0.03, outlier_fraction=0.02)
    cfg = _cfg(method)
    near = estimate_surface(patch.points, patch.hip, patch.camera_axis, cfg)
    far = estimate_surface(patch.points + FAR, patch.hip + FAR, patch.camera_axis, cfg)
    assert near.valid and far.valid
    assert np.allclose(far.centroid - FAR, near.centroid, atol=1e-3)
    assert np.degrees(np.arccos(min(1.0, far.normal @ near.normal))) < 0.1


@pytest.mark.parametrize("method", METHODS)
def test_nan_rows_are_dropped(method):
    pts = _grid_plane()
    dirty = pts.copy()
    dirty[::7] = np.nan
    dirty[1::11, 1] = np.inf
    clean = dirty[np.isfinite(dirty).all(1)]
    a = estimate_surface(dirty, HIP, CAM, _cfg(method))
    b = estimate_surface(clean, HIP, CAM, _cfg(method))
    assert a.valid and np.allclose(a.centroid, b.centroid) and np.allclose(a.normal, b.normal)


@settings(max_examples=8, deadline=None)
@given(offset=st.tuples(*[st.floats(-1e3, 1e3)] * 3).map(np.array))
def test_estimates_translate_with_any_offset(offset):
    patch = make_patch("ellipsoid", np.random.default_rng(12), hole_radius_m=0.03)
    for method in ("paper", "quadric"):
        near = estimate_surface(patch.points, patch.hip, patch.camera_axis, _cfg(method))
        moved = estimate_surface(
            patch.points + offset, patch.hip + offset, patch.camera_axis, _cfg(method)
        )
        assert np.linalg.norm(moved.centroid - offset - near.centroid) < 1e-3
        assert moved.normal @ near.normal > np.cos(np.radians(0.1))


@SETTINGS
@given(
    cloud=arrays(
        np.float64,
        st.tuples(st.integers(0, 60), st.just(3)),
        elements=st.one_of(st.floats(-0.2, 0.2), st.sampled_from([np.nan, np.inf, 0.0])),
    ),
    method=st.sampled_from(METHODS),
)
def test_arbitrary_clouds_never_raise_or_give_nan(cloud, method):
    _assert_finite(estimate_surface(cloud, [0.0, 0.0, 0.0], [0.3, -0.2, 1.0], _cfg(method)))


# ----- the paper's shells ------------------------------------------------------------------------


def test_shells_are_reported_and_the_worst_half_rejected():
    fit = estimate_surface(_grid_plane(), HIP, CAM, _cfg("paper", shell_mode="fixed", n_shells=5))
    assert fit.valid and fit.method == "paper"
    used = [s for s in fit.shells if s.valid]
    assert used[0].kind == "plane" and all(s.kind == "circle" for s in used[1:])
    assert sum(s.kept for s in used) == len(used) - len(used) // 2
    assert all(s.normal[2] > 0.99 for s in used)  # all face the camera
    for s in fit.shells:
        assert s.r_inner_m < s.r_outer_m
        if s.kind == "circle" and s.valid:
            assert s.radius_m > 0.0


def test_shells_with_one_or_two_points_are_reported_invalid():
    plane = _grid_plane()
    plane = plane[np.linalg.norm(plane - HIP, axis=1) > 0.075]  # nothing in the first shells ...
    sparse = HIP + np.array([[0.0, 0.0, -0.061], [0.003, 0.0, -0.062]])  # ... but two points
    cfg = _cfg("paper", shell_mode="fixed", r_in_m=0.055, n_shells=6, min_shell_points=3)
    fit = estimate_surface(np.vstack((plane, sparse)), HIP, CAM, cfg)
    assert fit.valid
    small = [s for s in fit.shells if s.n_points < 3]
    assert small and all(not s.valid and not s.kept for s in small)
    assert all(s.valid for s in fit.shells if s.n_points >= 30)
    assert np.allclose(fit.normal, [0, 0, 1], atol=1e-6)


def test_fixed_and_adaptive_shell_edges():
    d = np.array([0.07, 0.08, 0.1, 0.12])
    fixed = shell_edges(d, _cfg("paper", shell_mode="fixed", n_shells=4))
    assert fixed[0] == 0.0 and fixed[1] == pytest.approx(0.04) and fixed[-1] == pytest.approx(0.15)
    adaptive = shell_edges(d, _cfg("paper", n_shells=4, adaptive_span_m=0.02))
    assert len(adaptive) == 5 and adaptive[0] < 0.08 + 1e-12
    assert adaptive[-1] - adaptive[0] == pytest.approx(0.02, abs=1e-9)


def test_r_in_close_to_r_out_still_behaves():
    cfg = _cfg("paper", shell_mode="fixed", r_in_m=0.1499, r_out_m=0.15, n_shells=3)
    fit = estimate_surface(_grid_plane(), HIP, CAM, cfg)
    _assert_finite(fit)
    assert fit.valid  # the inner ball (0, r_in) holds the plane's nearest points
    assert np.allclose(fit.normal, [0, 0, 1], atol=1e-6)


def test_edge_on_normals_turn_towards_the_hip():
    """Camera axis in the surface's plane: n . z = 0, sign() would zero the normal."""
    pts = _grid_plane()
    side_cam = np.array([1.0, 0.0, 0.0])
    for method in METHODS:
        fit = estimate_surface(pts, HIP, side_cam, _cfg(method))
        assert fit.valid, (method, fit.reason)
        assert np.allclose(fit.normal, [0, 0, 1], atol=1e-6), method


def test_paper_method_is_biased_but_finite_on_a_curved_surface():
    rng = np.random.default_rng(3)
    errors = []
    for _ in range(6):
        patch = make_patch("sphere", rng, outlier_fraction=0.02)
        fit = estimate_surface(patch.points, patch.hip, patch.camera_axis, _cfg("paper"))
        assert fit.valid
        _assert_finite(fit)
        errors.append((fit.centroid - patch.closest) @ patch.normal)
    # Ring-circle centres sit inside a convex surface: reported deeper, by up to a few cm.
    assert np.median(errors) < 0.0
    assert np.all(np.abs(errors) < 0.04)


# ----- the nearest-point baseline ----------------------------------------------------------------


def test_nearest_point_baseline():
    pts = _grid_plane()
    fit = nearest_point(pts, HIP, CAM, k=15)
    assert fit.valid and fit.method == "nearest"
    assert np.min(np.linalg.norm(pts - fit.centroid, axis=1)) == 0.0  # an input point
    assert np.linalg.norm(fit.centroid - [0.01, -0.02, 0.0]) <= 0.004 * np.sqrt(0.5) + 1e-12
    assert np.allclose(fit.normal, [0, 0, 1])
    assert not nearest_point(pts[:2], HIP, CAM).valid
    with pytest.raises(ValueError, match="points"):
        nearest_point(pts[:, :2], HIP, CAM)


def test_surface_fit_placeholders_are_finite():
    fit = SurfaceFit(True, [np.nan, 0, 0], [0, 0, 1])
    assert not fit.valid and fit.reason
    bad = SurfaceFit(True, [0, 0, 0], [0, 0, 0], quality=np.nan)
    assert not bad.valid and np.allclose(bad.normal, [0, 0, 1]) and bad.quality == 0.0
    assert SurfaceFit(True, [0, 0, 0], [0, 0, 2], quality=3.0).quality == 1.0
