"""Where bodies meet: the crease scenes and the estimate that takes the nearer of two surfaces."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hapticloud.core.errors import InputError
from hapticloud.core.perception import (
    AbstractionConfig,
    CameraPipeline,
    PerceptionConfig,
    SurfaceFit,
    curvature,
    estimate_surface,
)
from hapticloud.core.sim import (
    ContactScene,
    contact_bench_scenes,
    finger_on_chest_scene,
    step_bench_scenes,
)
from hapticloud.core.studies import perception as study
from hypothesis import given
from hypothesis import strategies as st
from synthetic_patches import make_patch


def _cylinder_on_plane(rng: np.random.Generator, gap_m: float = 0.0) -> np.ndarray:
    """A plane x = 0 (the chest) and a cylinder r 4 cm along y lying on it (the forearm)."""
    yz = rng.uniform(-0.15, 0.15, size=(6000, 2))
    plane = np.column_stack((np.zeros(len(yz)), yz))
    theta = rng.uniform(-np.pi / 2, np.pi / 2, 2500)  # the half facing +x (the camera)
    y = rng.uniform(-0.15, 0.15, len(theta))
    r = 0.04
    cyl = np.column_stack((r + gap_m + r * np.cos(theta), y, r * np.sin(theta)))
    # The plane behind the cylinder is hidden from a camera on +x.
    plane = plane[np.abs(plane[:, 2]) > r]
    cloud = np.vstack((plane, cyl))
    return cloud + rng.normal(0.0, 0.0005, cloud.shape)


def test_the_nearer_of_two_surfaces_is_taken_not_a_blend():
    rng = np.random.default_rng(3)
    cloud = _cylinder_on_plane(rng)
    # Above the cylinder: the plane 60 mm away, the cylinder 4 mm nearer.
    hip = np.array([0.06, 0.0, 0.0])
    for z in (0.085, 0.09):
        hip = np.array([0.06, 0.0, z])
        d_cyl = np.hypot(hip[0] - 0.04, hip[2]) - 0.04
        fit = estimate_surface(cloud, hip, [-1.0, 0.0, 0.0])
        assert fit.valid
        err = fit.d_proj(hip, 0.0) - min(d_cyl, hip[0])
        assert err < 0.5e-3, (z, err)  # never the farther surface
        assert abs(err) < 1.5e-3, (z, err)
    one = estimate_surface(
        cloud,
        hip,
        [-1.0, 0.0, 0.0],
        AbstractionConfig()
        .replace_path("quadric.second_surface", False)
        .replace_path("quadric.narrowings", 0),
    )
    # Without the check (and without the narrower refit, which finds the cylinder too) the fit
    # keeps the plane (the larger surface): farther than the truth.
    assert one.d_proj(hip, 0.0) - min(d_cyl, hip[0]) > 1e-3


def test_a_single_surface_with_flying_pixels_stays_one_surface():
    rng = np.random.default_rng(5)
    xy = rng.uniform(-0.12, 0.12, size=(6000, 2))
    cloud = np.column_stack((xy, rng.normal(0.0, 0.0005, len(xy))))
    flying = cloud[:300].copy()
    flying[:, 2] += rng.uniform(0.002, 0.03, len(flying))
    cloud = np.vstack((cloud, flying))
    fit = estimate_surface(cloud, [0.0, 0.0, 0.06], [0.0, 0.0, -1.0])
    assert fit.valid and fit.surfaces == 1
    assert abs(fit.d_proj([0.0, 0.0, 0.06], 0.0) - 0.06) < 1e-3


@pytest.mark.parametrize("split", ["train", "heldout"])
def test_crease_paths_switch_the_closest_body(split):
    scenes = contact_bench_scenes(split)
    classes = {s.scene_class for s in scenes.values()}
    assert classes == {"crease", "thin_limb", "far_body"}
    for scene in scenes.values():
        if scene.scene_class != "crease":
            continue
        bodies = {scene.world.ground_truth(h).body for h in scene.hip_track(30, 0, 15)}
        assert len(bodies) == 2, scene.name


def test_strap_paths_cross_from_the_plate_onto_the_strap_and_off():
    for scene in step_bench_scenes().values():
        assert scene.scene_class == "thin_step"
        track = scene.hip_track(30, 0, 15)
        bodies = [scene.world.ground_truth(h).body for h in track]
        assert bodies[0] == bodies[14] == "torso", scene.name
        assert "strap" in bodies, scene.name


def test_the_step_table_reports_the_optimistic_side_and_judges_nothing():
    scenes = dict(list(step_bench_scenes().items())[:1])
    steps = study.contact_study(15, None, "strap", scenes, ("thin_step",))
    assert list(steps["classes"]) == ["thin_step"]
    row = steps["classes"]["thin_step"]
    (scene_row,) = steps["scenes"].values()
    assert scene_row["frames"] == row["frames"] == 15
    text = study.format_contact(steps, study.STEP_TITLE, targets=False)
    assert "PASS" not in text and "FAIL" not in text
    optimistic = text[text.index("optimistic side") :].splitlines()[1].split()
    assert optimistic == [
        "thin_step",
        f"{row['dproj_unsafe_p90_mm']:+.2f}",
        f"{row['dproj_max_mm']:+.2f}",
        f"{100 * row['optimistic_share']:.1f}",
        "%",
    ]
    assert study.format_contact(steps).count("[") == len(study.check_contact_targets(steps))


def test_a_class_without_scenes_fails_its_targets():
    steps = study.contact_study(15, None, "strap", dict(list(step_bench_scenes().items())[:1]))
    assert list(steps["classes"]) == ["crease", "thin_limb", "far_body"]
    assert not any(study.check_contact_targets(steps).values())


def _bench_row(scene: ContactScene) -> dict:
    """One scene's row of :func:`study.contact_study`, its 60 frames rendered as the bench
    renders them."""
    return study.contact_study(60, None, "one", {scene.name: scene})["scenes"][scene.name]


def test_a_strap_on_the_chest_is_not_smoothed_into_it() -> None:
    # The bench's worst strap (10 mm high, 20 mm wide), its 60 frames rendered as the bench
    # does: the wide fit runs between the levels, and the strap's top then makes a second
    # surface that sags with its sides, or fails the inlier test and the fit that kept the
    # plate stands. Without the nearest patch's answer: +7.5 mm at worst, bias +1.29 mm (with
    # it +3.6 and +0.23).
    row = _bench_row(step_bench_scenes()["strap_10mm_high_20mm_wide"])
    assert row["dproj_max_mm"] < 5.0
    assert row["dproj_bias_mm"] < 0.6


def test_a_strap_at_the_sensors_resolution_is_not_dropped_as_noise() -> None:
    # A strap 2 mm high and 10 mm wide against 1.7 mm of depth noise: its nearer points lie
    # among the plate's noise tail, and a nearer surface cannot be told from that tail. The
    # thirteenth session's gate that took scattered nearer points for noise (built, not
    # shipped) fixed two pessimistic plate frames and made this strap's 60 bench frames
    # optimistic: p90 +0.79 -> +1.33 mm, frames over +0.5 mm 13.3 -> 20.0 % (the gate's commit
    # kept out of the history; its figures in docs/benchmarks.md).
    row = _bench_row(step_bench_scenes()["strap_2mm_high_10mm_wide"])
    assert row["dproj_unsafe_p90_mm"] < 1.0
    assert row["optimistic_share"] < 0.17


@pytest.mark.parametrize("gap_m", [0.0, 0.002])
def test_a_finger_lying_on_the_chest_is_not_reported_farther(gap_m: float) -> None:
    # A crease where one body is finger-thin (r 12 mm), 0.75 m from the camera: the fit held to
    # the 0.5 mm floor explains 31-41 % of the chest's points (1.7 mm of noise), and the finger
    # explains 42-63 % of its own. Held to a fixed 70 % the finger was outliers and the chest
    # answered, 3.4-4.5 mm too far: bias +0.93 / +1.39 mm over the 60 frames (gap 0 / 2 mm).
    # Its flank seen edge-on, 29-67 points nearer than the chest that make no surface the fit
    # accepts, with the chest 4 mm farther: held no farther than those points, |d_proj err| p90
    # 3.45 / 3.87 -> 1.85 / 1.54 mm and the worst frame +4.2 -> +2.0 / +1.8 mm.
    row = _bench_row(finger_on_chest_scene(gap_m))
    assert row["dproj_bias_mm"] < 0.5
    assert row["valid_near"] >= 0.95
    assert row["dproj_mm_p90"] < 3.0
    assert row["dproj_max_mm"] < 3.0


def _nearer_points(rng: np.random.Generator, spread_m: float, n: int = 40) -> np.ndarray:
    """``n`` points 50-52 mm below a HIP at the origin, spread over ``spread_m`` square."""
    xy = rng.uniform(-spread_m / 2, spread_m / 2, size=(n, 2))
    return np.column_stack((xy, -0.05 - rng.uniform(0.0, 0.002, n)))


def test_nearer_points_that_lie_together_bound_the_answer_and_scattered_ones_do_not() -> None:
    rng = np.random.default_rng(11)
    qc = AbstractionConfig().quadric
    k = qc.second_surface_min_points
    together = _nearer_points(rng, 0.012)  # a finger's flank: pixels side by side
    d2 = np.einsum("ij,ij->i", together, together)
    level = curvature._unmodelled_nearer_m(together, qc)
    assert level == pytest.approx(np.sqrt(np.sort(d2)[k - 1]))
    scattered = _nearer_points(rng, 0.2)  # stray pixels over the patch: no surface
    assert curvature._unmodelled_nearer_m(scattered, qc) == np.inf
    for few in (together[: k - 1], np.empty((0, 3))):
        assert curvature._unmodelled_nearer_m(few, qc) == np.inf
    # Thousands of them: the nearest max_points decide (the k-d tree of all costs milliseconds).
    many = _nearer_points(rng, 0.06, n=5000)
    d2 = np.einsum("ij,ij->i", many, many)
    every_one = AbstractionConfig().replace_path("quadric.max_points", 100000).quadric
    level = curvature._unmodelled_nearer_m(many, qc)
    assert level == curvature._unmodelled_nearer_m(many, every_one)
    assert level == pytest.approx(np.sqrt(np.sort(d2)[k - 1]))
    # Fewer points kept than the count that stands for a surface would switch the bound off.
    strict = (
        AbstractionConfig()
        .replace_path("quadric.max_points", 20)
        .replace_path("quadric.second_surface_min_points", 100)
        .quadric
    )
    assert np.isfinite(curvature._unmodelled_nearer_m(many, strict))


@given(
    st.floats(0.0, 0.2),
    st.floats(0.0, 0.3),
    st.floats(-1.0, 1.0),
    st.floats(-1.0, 1.0),
)
def test_an_answer_held_to_nearer_points_never_moves_farther(
    dist: float, level: float, nx: float, ny: float
) -> None:
    normal = np.array([nx, ny, 1.0]) / np.linalg.norm([nx, ny, 1.0])
    hip = np.array([0.3, -0.2, 1.1])
    fit = SurfaceFit(True, hip - dist * normal, normal, "fitted")
    held = curvature._held_no_farther(fit, level, hip)
    assert np.allclose(held.normal, fit.normal, rtol=0.0, atol=1e-12)
    assert held.d_proj(hip, 0.0) <= fit.d_proj(hip, 0.0) + 1e-12
    assert held.d_proj(hip, 0.0) == pytest.approx(min(dist, level), abs=1e-9)
    if level > dist + 1e-9:
        assert held is fit
    elif level < dist - 1e-9:
        assert "held" in held.reason and held.reason.startswith("fitted; ")


def test_the_finger_path_crosses_from_the_chest_onto_the_finger() -> None:
    scene = finger_on_chest_scene()
    track = scene.hip_track(60, 7, study.SEGMENT_FRAMES)
    bodies = {scene.world.ground_truth(hip, 0.0).body for hip in track}
    assert bodies == {"torso", "finger"}
    with pytest.raises(InputError, match="gap_m"):
        finger_on_chest_scene(-0.001)


def test_train_and_heldout_scenes_differ():
    train, held = contact_bench_scenes("train"), contact_bench_scenes("heldout")
    assert not set(train) & set(held)
    with pytest.raises(ValueError):
        contact_bench_scenes("test")


def _ridge(rng: np.random.Generator, noise_m: float) -> np.ndarray:
    """A convex ridge along y: z = 0 for x < 0, falling at 80 deg for x > 0 (a box's edge)."""
    x, y = rng.uniform(-0.15, 0.15, 8000), rng.uniform(-0.15, 0.15, 8000)
    z = np.where(x < 0, 0.0, -np.tan(np.radians(80.0)) * x)
    return np.column_stack((x, y, z + rng.normal(0.0, noise_m, len(x))))


def test_an_edge_inside_the_bandwidth_is_fitted_again_narrower() -> None:
    hip = np.array([-0.01, 0.0, 0.05])  # above the flat side, 10 mm from the edge
    cloud = _ridge(np.random.default_rng(1), 0.0005)
    wide_cfg = AbstractionConfig().replace_path("quadric.narrowings", 0)
    wide = estimate_surface(cloud, hip, [0.0, 0.0, -1.0], wide_cfg)
    fit = estimate_surface(cloud, hip, [0.0, 0.0, -1.0])
    assert wide.valid and fit.valid
    assert wide.quality < 0.5 <= fit.quality  # the edge smoothed over, then modelled locally
    assert fit.residual_m < 0.6 * wide.residual_m
    assert abs(fit.d_proj(hip, 0.0) - 0.05) < 0.3e-3 < abs(wide.d_proj(hip, 0.0) - 0.05)


def test_noise_alone_does_not_narrow_the_fit() -> None:
    """A far body's noise lowers the quality too, but a narrower fit would only be noisier: its
    residual is not much smaller, so the wide fit answers."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.15, 0.15, size=(8000, 2))
    cloud = np.column_stack((xy, rng.normal(0.0, 0.004, len(xy))))
    hip = np.array([0.0, 0.0, 0.05])
    wide_cfg = AbstractionConfig().replace_path("quadric.narrowings", 0)
    wide = estimate_surface(cloud, hip, [0.0, 0.0, -1.0], wide_cfg)
    fit = estimate_surface(cloud, hip, [0.0, 0.0, -1.0])
    assert wide.quality < 0.5  # the noise is 8x the floor: a narrower fit is tried
    assert np.array_equal(fit.centroid, wide.centroid) and fit.quality == wide.quality


# Frames of the demo (`hapticloud run demo`, the estimator's input after stages A-D, with the
# truth): "medial" and "hidden", the hand between the torso's top edge and the chin, about 70 mm
# from both; "hole", the hand on the cheek hiding the 28 mm around the closest point (the front
# camera decimated 8x, `bench safety`); "corner", the app's live demo (right45, its second camera
# until the tenth session, recorded by `hapticloud app --record`), the hand 72 mm from the
# torso's top edge, the chin and the neck about as near.
_SWITCH_FRAMES = Path(__file__).parent / "data" / "demo_body_switch_frames.npz"


def _switch_frame(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    data = np.load(_SWITCH_FRAMES)
    return (
        data[f"{name}_points"],
        data[f"{name}_hip"],
        data[f"{name}_axis"],
        float(data[f"{name}_true_distance"]),
    )


def test_a_hip_equally_near_two_bodies_gets_one_of_them_not_a_blend() -> None:
    points, hip, axis, truth = _switch_frame("medial")
    one_fit = AbstractionConfig().replace_path("quadric.narrowings", 0)
    blend = estimate_surface(
        points, hip, axis, one_fit.replace_path("quadric.second_surface", False)
    )
    assert blend.quality < 0.3  # the shell of nearest points holds both bodies: a blend
    # Either way out of it takes one body: the second-surface check in the wide fit (the noise
    # measured around the nearest points' centroid), or the narrower fit from the nearest patch.
    for cfg in (
        one_fit,
        one_fit.replace_path("quadric.second_surface", False).replace_path("quadric.narrowings", 1),
    ):
        fit = estimate_surface(points, hip, axis, cfg)
        assert fit.valid and fit.quality >= 0.5
        err = fit.d_proj(hip, 0.0) - truth
        assert -1e-3 < err < 0.6e-3
    fit = estimate_surface(points, hip, axis)
    assert fit.valid and fit.quality >= 0.5
    assert -1e-3 < fit.d_proj(hip, 0.0) - truth < 0.6e-3


def test_the_nearest_patch_gives_way_when_the_other_points_make_a_nearer_surface(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The hand hides the torso's edge from this camera: the nearest points it sees are the
    # chin's, 11 mm farther than the edge; the torso's faces around the edge come nearer.
    points, hip, axis, truth = _switch_frame("hidden")
    fit = estimate_surface(points, hip, axis)
    assert not (fit.valid and fit.quality >= 0.5 and fit.d_proj(hip, 0.0) - truth > 0.5e-3)
    monkeypatch.setattr(curvature, "_rest_nearer", lambda *args: "")
    unchecked = estimate_surface(points, hip, axis)
    assert unchecked.quality >= 0.5 and unchecked.d_proj(hip, 0.0) - truth > 5e-3


def test_a_narrower_fit_answers_where_the_wide_fit_kept_a_minority_of_its_points() -> None:
    # Three surfaces in the workspace: the wide fit keeps 13 % of its points, so its residual
    # (from those) is small and the narrower fit, which explains nearly all of its own, failed
    # the residual rule. Both cameras lost their estimates so for 84 ms in the app: a hold.
    points, hip, axis, truth = _switch_frame("corner")
    wide = estimate_surface(
        points, hip, axis, AbstractionConfig().replace_path("quadric.narrowings", 0)
    )
    assert wide.inliers < 0.5 and wide.quality < 0.5
    fit = estimate_surface(points, hip, axis)
    assert fit.valid and fit.quality >= 0.5 and fit.inliers >= 0.9
    err = fit.d_proj(hip, 0.0) - truth
    assert -1e-3 < err < 0.5e-3  # on the safe side, within a millimetre


def test_a_narrower_fit_does_not_bridge_a_hole_wider_than_its_bandwidth() -> None:
    points, hip, axis, truth = _switch_frame("hole")
    wide_cfg = AbstractionConfig().replace_path("quadric.narrowings", 0)
    wide = estimate_surface(points, hip, axis, wide_cfg)
    assert wide.quality < 0.5 and wide.d_proj(hip, 0.0) < truth  # low quality, safe side
    narrow = estimate_surface(
        points, hip, axis, wide_cfg.replace_path("quadric.bandwidth_m", 0.0175)
    )
    assert narrow.quality > wide.quality and narrow.d_proj(hip, 0.0) - truth > 3e-3  # a guess
    fit = estimate_surface(points, hip, axis)
    assert np.array_equal(fit.centroid, wide.centroid) and fit.quality == wide.quality


def test_narrowings_stop_at_the_narrowest_bandwidth() -> None:
    # 35 mm halved 3 times would be 4.4 mm: the third level is skipped (and nothing crashes);
    # a bandwidth set under 10 mm with one narrowing fits at that bandwidth alone.
    points, hip, axis, _ = _switch_frame("medial")
    three = AbstractionConfig().replace_path("quadric.narrowings", 3)
    two = AbstractionConfig().replace_path("quadric.narrowings", 2)
    a, b = estimate_surface(points, hip, axis, three), estimate_surface(points, hip, axis, two)
    assert np.array_equal(a.centroid, b.centroid) and a.quality == b.quality
    narrow = AbstractionConfig().replace_path("quadric.bandwidth_m", 0.008)
    alone = narrow.replace_path("quadric.narrowings", 0)
    c, d = estimate_surface(points, hip, axis, narrow), estimate_surface(points, hip, axis, alone)
    assert np.array_equal(c.centroid, d.centroid) and c.quality == d.quality


def test_a_normal_pointing_away_from_the_hip_is_never_an_estimate() -> None:
    # The HIP "behind" a plane as its camera sees it: the fit's normal faces the camera, away
    # from the HIP (at a crease, a patch seen edge-on does this): d_proj would be
    # -(distance + r_hip), and the constraint would push the HIP into the body.
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.1, 0.1, size=(5000, 2))
    cloud = np.column_stack((xy, rng.normal(0.0, 0.0005, len(xy))))
    hip, axis = np.array([0.0, 0.0, -0.05]), [0.0, 0.0, -1.0]
    fit = estimate_surface(cloud, hip, axis)
    assert fit.valid and fit.normal[2] > 0.9  # the fit alone faces the camera
    for method in ("quadric", "paper", "nearest"):
        config = PerceptionConfig().replace_path("abstraction.method", method)
        est = CameraPipeline(config).process(cloud, hip, axis, t=0.0)
        assert not est.valid and "points away from the HIP" in est.reason, method


def test_a_fit_across_the_occluded_cheek_moves_to_the_bulge_it_smoothed_over(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The demo (seed 9, right45, its second camera then, at 6.78 s): the hand hides 12 mm around
    # the cheek's closest point, and the fit across the hole, standing on the face and the head
    # around it, puts the surface 17 mm farther than it is with a quality over the gate (0.61).
    # Its residual is 7x the noise: a narrower fit from the nearest patch follows the bulge, and
    # the answer moves.
    data = np.load(Path(__file__).parent / "data" / "demo_cheek_hole_frame.npz")
    points, hip, axis = data["cheek_points"], data["cheek_hip"], data["cheek_axis"]
    truth = float(data["cheek_true_distance"])
    fit = estimate_surface(points, hip, axis)
    assert fit.valid and fit.quality >= 0.5 and "nearer across" in fit.reason
    assert -3e-3 < fit.d_proj(hip, 0.0) - truth < 0.5e-3
    monkeypatch.setattr(curvature, "_nearer_across_a_hole", lambda best, *args: best)
    bridged = estimate_surface(points, hip, axis)
    assert bridged.quality >= 0.5 and bridged.d_proj(hip, 0.0) - truth > 10e-3


@pytest.mark.parametrize("shape", ["sphere", "ellipsoid", "cylinder", "plane"])
def test_a_smooth_body_seen_around_a_hole_is_not_moved(
    shape: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Around the hand's hole on one smooth body the fit's residual is the noise: a narrower fit
    # from the rim (it extrapolated a head 9 mm nearer, and the hand bounced) must not answer.
    rng = np.random.default_rng(5)
    patches = [
        make_patch(shape, rng, hole_radius_m=radius, outlier_fraction=0.02)
        for radius in (0.015, 0.02, 0.025, 0.03)
        for _ in range(4)
    ]
    fits = [estimate_surface(p.points, p.hip, p.camera_axis) for p in patches]
    monkeypatch.setattr(curvature, "_nearer_across_a_hole", lambda best, *args: best)
    for patch, fit in zip(patches, fits, strict=True):
        plain = estimate_surface(patch.points, patch.hip, patch.camera_axis)
        assert "nearer across" not in fit.reason
        assert np.array_equal(fit.centroid, plain.centroid)
