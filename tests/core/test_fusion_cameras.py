"""Two cameras that disagree: weighting by measured residual, disagreement in the fused quality,
the nearer surface answering; and the simulated calibration error."""

from __future__ import annotations

import numpy as np
from hapticloud.core.fusion import FusionConfig, SurfaceFusion
from hapticloud.core.perception.estimate import SurfaceEstimate
from hapticloud.core.sim.scenes import miscalibrated_pose

UP = (0.0, 0.0, 1.0)
HIP = (0.0, 0.0, 0.55)


def feed(offsets, noise, residual, cfg=None, T=0.6, seed=0):
    """Two cameras at 30 Hz (staggered) on a still plane z = 0.5; camera i reports it shifted by
    ``offsets[i]`` along its normal with ``noise[i]`` (m) and ``residual[i]``; 800 Hz samples."""
    rng = np.random.default_rng(seed)
    fusion = SurfaceFusion(cfg or FusionConfig())
    arrivals = sorted(
        (k / 30.0 + i / 60.0, i)
        for i in range(2)
        for k in range(int(T * 30))
        if k / 30 + i / 60 <= T
    )
    out, j = [], 0
    for tick in range(int(T * 800) + 1):
        t = tick / 800.0
        while j < len(arrivals) and arrivals[j][0] <= t:
            te, i = arrivals[j]
            z = 0.5 + offsets[i] + rng.normal(0.0, noise[i])
            fusion.add(
                SurfaceEstimate(
                    te, f"cam{i}", (0.0, 0.0, z), UP, True, hip=HIP, residual_m=residual[i]
                )
            )
            j += 1
        out.append(fusion.sample(t))
    return out


def test_cameras_that_disagree_are_flagged_and_the_nearer_surface_answers() -> None:
    # cam1 puts the plane 4 mm farther from the HIP (a calibration error): cam0 answers.
    out = feed((0.0, -0.004), (0.0002, 0.0002), (0.001, 0.001))
    late = [o for o in out if o.t > 0.3]
    assert all(o.disagree for o in late)
    assert all(o.agreement.dropped == ("cam1",) for o in late)
    assert all(abs(o.disagreement_m - 0.004) < 0.001 for o in late)
    assert all(abs(o.centroid[2] - 0.5) < 0.0007 for o in late)  # never the farther plane
    assert "disagree" in late[-1].quality_note and late[-1].valid and late[-1].reason == ""
    # The other way round: cam1 nearer, cam1 answers.
    out = feed((0.0, +0.004), (0.0002, 0.0002), (0.001, 0.001))
    assert all(abs(o.centroid[2] - 0.504) < 0.0007 for o in out if o.t > 0.3)


def test_cameras_within_their_noise_agree() -> None:
    out = feed((0.0, -0.0005), (0.0005, 0.0005), (0.001, 0.001))
    late = [o for o in out if o.t > 0.3]
    assert not any(o.disagree for o in late)
    assert all(o.cameras == ("cam0", "cam1") for o in late)


def test_a_noisier_camera_weighs_less() -> None:
    def error(cfg):
        errs = []
        for seed in range(4):
            out = feed((0.0, 0.0), (0.0003, 0.004), (0.0008, 0.006), cfg=cfg, seed=seed)
            errs += [abs(o.target_centroid[2] - 0.5) for o in out if o.t > 0.3]
        return float(np.median(errs))

    weighted = error(FusionConfig(disagreement_sigmas=20.0))
    plain = error(FusionConfig(weigh_cameras=False))
    assert weighted < 0.5 * plain
    out = feed(
        (0.0, 0.0), (0.0003, 0.004), (0.0008, 0.006), cfg=FusionConfig(disagreement_sigmas=20.0)
    )
    w = dict(zip(out[-1].agreement.cameras, out[-1].agreement.weights, strict=True))
    assert w["cam0"] > 0.95 > 0.05 > w["cam1"]


def test_one_camera_has_no_agreement_and_the_plain_fit() -> None:
    rng = np.random.default_rng(1)
    a, b = SurfaceFusion(FusionConfig()), SurfaceFusion(FusionConfig(weigh_cameras=False))
    for k in range(20):
        e = SurfaceEstimate(
            k / 30, "solo", (0.0, 0.0, 0.5 + rng.normal(0, 1e-3)), UP, True, residual_m=1e-3
        )
        a.add(e)
        b.add(e)
        fa, fb = a.sample(k / 30 + 0.01), b.sample(k / 30 + 0.01)
        assert np.array_equal(fa.centroid, fb.centroid) and np.array_equal(fa.normal, fb.normal)
        assert fa.disagreement_m == 0.0 and not fa.disagree and fa.quality_note == ""


def test_miscalibrated_pose_moves_the_pivot_by_the_shift_and_turns_by_the_angle() -> None:
    pose = np.eye(4)
    pose[:3, 3] = (0.75, 0.0, 1.2)
    pivot = np.array([0.0, 0.0, 1.0])
    believed = miscalibrated_pose(pose, shift_m=0.003, angle_deg=1.0, pivot=pivot)
    seen = np.linalg.inv(pose) @ np.append(pivot, 1.0)
    assert abs(np.linalg.norm((believed @ seen)[:3] - pivot) - 0.003) < 1e-12
    turn = believed[:3, :3] @ pose[:3, :3].T
    assert abs(np.degrees(np.arccos((np.trace(turn) - 1) / 2)) - 1.0) < 1e-9
    at_camera = miscalibrated_pose(pose, shift_m=0.0, angle_deg=1.0)
    assert np.allclose(at_camera[:3, 3], pose[:3, 3])
