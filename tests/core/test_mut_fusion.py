"""SurfaceFusion pinned down where mutation testing found it loose (docs/testing.md): the invalid
fit, holding the last output (not jumping) when the data goes stale and the held target at the
extrapolation horizon, the exact boundaries of staleness, of the horizon, of the late window and of
the follower's restart, the speed limit ``max_speed_m_s * dt``, ``max_samples`` keeping the newest
(ties by arrival), the configuration reaching the fit, the free-space proofs, and the caches that
keep a tick to one polynomial evaluation and a held output to no new arrays."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hapticloud.core.errors import InputError
from hapticloud.core.fusion import FusionConfig, SurfaceFusion, fit_window
from hapticloud.core.fusion.regression import PolyFit
from hapticloud.core.perception.estimate import SurfaceEstimate

DT = 1.0 / 800.0
UP = (0.0, 0.0, 1.0)


def est(t, c, n=UP, cam="a", valid=True, **kw) -> SurfaceEstimate:
    return SurfaceEstimate(t=t, camera=cam, centroid=c, normal=n, valid=valid, **kw)


def proof(t: float, free_m: float, hip=(0.0, 0.0, 1.0), cam: str = "a") -> SurfaceEstimate:
    """An invalid estimate of a camera that saw its workspace empty."""
    return est(t, (0.0, 0.0, 0.0), cam=cam, valid=False, hip=hip, free_m=free_m)


@pytest.fixture
def evaluations(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """Times at which any PolyFit was evaluated."""
    calls: list[float] = []
    original = PolyFit.evaluate

    def counting(self: PolyFit, t: float):
        calls.append(t)
        return original(self, t)

    monkeypatch.setattr(PolyFit, "evaluate", counting)
    return calls


# ----- the invalid fit -----------------------------------------------------------------------
def test_an_invalid_fit_is_reported_invalid_and_holds_the_last_output() -> None:
    fusion = SurfaceFusion()
    assert fusion.add(est(0.0, (0.1, 0.2, 0.3), (0.0, 1.0, 0.0))) is True
    before = fusion.sample(0.001)
    assert before.valid and before.centroid.tolist() == [0.1, 0.2, 0.3]
    with np.errstate(over="ignore", invalid="ignore"):
        fusion.add(est(0.01, (1e308, 0.0, 0.0)))
        fusion.add(est(0.02, (-1e308, 0.0, 0.0), cam="b"))
        out = fusion.sample(0.0215)
    assert fusion.fit is not None and not fusion.fit.valid
    assert out.valid is False and out.stale is False
    assert out.reason == "regression failed (non-finite coefficients)"
    assert out.t == 0.0215 and out.age_s == pytest.approx(0.0015)
    np.testing.assert_array_equal(out.centroid, before.centroid)
    np.testing.assert_array_equal(out.normal, before.normal)
    np.testing.assert_array_equal(out.velocity, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(out.target_normal, UP)  # the newest estimate's normal
    assert (out.n_samples, out.degree, out.cameras) == (3, 0, ("a", "b"))
    assert all(np.isfinite(v).all() for v in (out.centroid, out.target_centroid))


def test_an_invalid_fit_restarts_the_followers_at_the_next_valid_target() -> None:
    cfg = FusionConfig(max_speed_m_s=0.01)
    fusion = SurfaceFusion(cfg)
    fusion.add(est(0.0, (0.0, 0.0, 0.0)))
    fusion.sample(0.001)
    with np.errstate(over="ignore", invalid="ignore"):
        fusion.add(est(0.01, (1e308, 0.0, 0.0)))
        assert not fusion.sample(0.011).valid
    # Much later, a surface 5 cm away: output starts there (no slow glide at 1 cm/s).
    fusion.add(est(1.0, (0.05, 0.0, 0.0)))
    out = fusion.sample(1.0 + DT)
    assert out.valid and out.centroid.tolist() == [0.05, 0.0, 0.0]


# ----- stale: hold, do not jump ----------------------------------------------------------------
def _lagging(evals: list[float] | None = None):
    """A slow follower (1 cm/s) behind a 5 cm step that arrives just before the data stops."""
    cfg = FusionConfig(max_speed_m_s=0.01, max_age_s=0.25, max_extrapolation_s=0.0625)
    fusion = SurfaceFusion(cfg)
    for k in range(7):
        fusion.add(est(k / 30, (0.0, 0.0, 0.5)))
    fusion.add(est(0.25, (0.05, 0.0, 0.5)))
    outs = [fusion.sample(k * DT) for k in range(1, int(0.7 / DT))]
    return cfg, fusion, outs


def test_stale_output_holds_the_last_valid_output_and_the_target_at_the_horizon() -> None:
    cfg, fusion, outs = _lagging()
    valid = [o for o in outs if o.valid]
    stale = [o for o in outs if not o.valid]
    assert stale and all(o.stale is True and o.valid is False for o in stale)
    last = valid[-1]
    assert last.target_centroid[0] - last.centroid[0] > 0.02  # far behind its target
    fit = fusion.fit
    assert fit is not None
    tc, tn, _ = fit.evaluate(fit.t_ref + cfg.max_extrapolation_s)
    for o in stale:
        np.testing.assert_array_equal(o.centroid, last.centroid)  # held, not jumped
        np.testing.assert_array_equal(o.normal, last.normal)
        np.testing.assert_array_equal(o.target_centroid, tc)
        np.testing.assert_array_equal(o.target_normal, tn)
        np.testing.assert_array_equal(o.velocity, [0.0, 0.0, 0.0])
        assert o.age_s > cfg.max_age_s and o.n_samples == 8 and o.cameras == ("a",)
        assert o.reason.startswith("stale: no valid estimate for ")
    assert stale[0].t == pytest.approx(last.t + DT)


def test_a_held_output_costs_no_evaluation_and_no_new_arrays(evaluations: list[float]) -> None:
    cfg = FusionConfig(max_age_s=0.25, max_extrapolation_s=0.0625)
    fusion = SurfaceFusion(cfg)
    for k in range(4):
        fusion.add(est(k / 30, (0.01 * k, 0.0, 0.5)))
    fusion.sample(0.1)
    stale = [fusion.sample(0.4 + k * DT) for k in range(20)]
    assert all(o.stale for o in stale)
    held_evaluations = [t for t in evaluations if t == pytest.approx(0.1 + 0.0625)]
    assert len(held_evaluations) == 1  # the same fit at the same capped time: evaluated once
    for a, b in itertools.pairwise(stale):
        assert a.centroid is b.centroid and a.target_centroid is b.target_centroid
        assert a.normal is b.normal and a.velocity is b.velocity
        assert a.seq + 1 == b.seq


def test_a_following_tick_evaluates_the_polynomial_once(evaluations: list[float]) -> None:
    fusion = SurfaceFusion()
    for k in range(5):
        fusion.add(est(k / 30, (0.1 * k / 30, 0.0, 0.5)))
    fusion.sample(4 / 30)
    fusion.sample(4 / 30 + DT)  # the first follow after the fit
    evaluations.clear()
    for k in range(2, 12):
        assert fusion.sample(4 / 30 + k * DT).valid
    assert len(evaluations) == 10


# ----- exact boundaries ------------------------------------------------------------------------
def test_stale_only_beyond_max_age() -> None:
    fusion = SurfaceFusion(FusionConfig(max_age_s=0.25, max_extrapolation_s=0.0625))
    fusion.add(est(0.5, (0.0, 0.0, 0.5)))
    at = fusion.sample(0.75)
    assert at.valid is True and at.stale is False and at.age_s == 0.25
    assert at.reason.startswith("holding")
    beyond = fusion.sample(0.75 + 1e-9)
    assert not beyond.valid and beyond.stale


def test_extrapolation_up_to_the_horizon_then_holding() -> None:
    fusion = SurfaceFusion(FusionConfig(max_extrapolation_s=0.0625))
    fusion.add(est(0.25, (0.0, 0.0, 0.5)))
    fusion.add(est(0.5, (0.125, 0.0, 0.5)))
    fresh = fusion.sample(0.5)
    assert fresh.reason == "" and fresh.valid is True and fresh.stale is False
    at = fusion.sample(0.5625)  # exactly t_ref + max_extrapolation_s
    assert at.reason == "" and at.velocity[0] == pytest.approx(0.5)
    assert at.target_centroid[0] == pytest.approx(0.15625)
    past = fusion.sample(0.5625 + 1.0 / 1024)
    assert past.reason == "holding: newest estimate 0.063 s old (max_extrapolation_s reached)"
    np.testing.assert_array_equal(past.velocity, [0.0, 0.0, 0.0])
    assert past.target_centroid[0] == pytest.approx(0.15625)


def test_the_followers_restart_only_beyond_reset_dt() -> None:
    def second_output(t1: float) -> tuple[float, float]:
        fusion = SurfaceFusion(FusionConfig(reset_dt_s=0.125, max_speed_m_s=0.01))
        fusion.add(est(0.0, (0.0, 0.0, 0.0)))
        fusion.sample(0.0)
        fusion.add(est(t1, (0.0625, 0.0, 0.0)))
        out = fusion.sample(t1)
        return out.centroid[0], out.target_centroid[0]

    y, target = second_output(0.125)  # exactly reset_dt: followed, speed-limited
    assert target == pytest.approx(0.0625)
    assert y == pytest.approx(0.01 * 0.125)
    y, target = second_output(0.125 + 1.0 / 1024)  # beyond: restarted at the target
    assert y == target


def test_the_speed_limit_is_max_speed_times_dt() -> None:
    cfg = FusionConfig(max_speed_m_s=0.05)
    fusion = SurfaceFusion(cfg)
    for k in range(6):
        fusion.add(est(k / 30, (0.0, 0.0, 0.5)))
    fusion.sample(5 / 30)
    fusion.add(est(6 / 30, (0.03, 0.04, 0.5)))  # a 5 cm step in x and y
    xs = [fusion.sample(5 / 30 + k * DT).centroid for k in range(1, 41)]
    steps = np.linalg.norm(np.diff(xs, axis=0), axis=1)
    assert steps.max() <= 0.05 * DT * (1 + 1e-9)
    assert steps.min() == pytest.approx(0.05 * DT)  # still far: every tick at the limit


# ----- the window ------------------------------------------------------------------------------
def test_above_max_samples_the_newest_are_kept() -> None:
    fusion = SurfaceFusion(FusionConfig(max_samples=8))
    for k in range(30):
        x = 0.01 if k >= 22 else 0.0
        fusion.add(est(k * 0.005, (x, 0.0, 0.0), cam=f"c{k:02d}"))
    out = fusion.sample(29 * 0.005)
    assert out.n_samples == 8
    assert out.cameras == tuple(f"c{k:02d}" for k in range(22, 30))
    assert out.target_centroid[0] == pytest.approx(0.01)


def test_equal_times_at_the_cut_keep_the_first_arrivals() -> None:
    fusion = SurfaceFusion(FusionConfig(max_samples=4))
    for k in range(40):
        fusion.add(est(0.0 if k < 10 else 0.125, (0.0, 0.0, 0.0), cam=f"c{k:02d}"))
    assert fusion.sample(0.125).cameras == ("c10", "c11", "c12", "c13")


def test_an_estimate_at_the_window_edge_is_out_of_the_fit() -> None:
    fusion = SurfaceFusion(FusionConfig(window_s=0.25))
    fusion.add(est(0.0, (0.0, 0.0, 0.0)))
    fusion.add(est(0.25, (0.01, 0.0, 0.0)))
    out = fusion.sample(0.25)
    assert out.n_samples == 1 and out.degree == 0


def test_late_and_gap_boundaries_of_add() -> None:
    fusion = SurfaceFusion(FusionConfig(window_s=0.25))
    assert fusion.add(est(0.5, (0.0, 0.0, 0.0)))
    assert not fusion.add(est(0.25, (0.0, 0.0, 0.0)))  # exactly window_s old: late
    assert not fusion.add(est(0.125, (0.0, 0.0, 0.0)))
    assert fusion.n_late == 2 and fusion.n_added == 3
    # a gap of exactly max_age_s keeps the window; a longer one drops it
    fusion = SurfaceFusion(FusionConfig(max_age_s=0.25, max_extrapolation_s=0.0625))
    fusion.add(est(0.0, (0.0, 0.0, 0.0)))
    fusion.add(est(0.25, (0.0, 0.0, 0.0)))
    assert fusion.sample(0.25).n_samples == 2
    fusion.add(est(0.5 + 1e-9, (0.0, 0.0, 0.0)))
    assert fusion.sample(0.5 + 1e-9).n_samples == 1


def test_the_configuration_reaches_the_fit() -> None:
    cfg = FusionConfig(
        weighting="inverse", max_degree=1, normal_max_degree=0, time_resolution_s=0.004
    )
    fusion = SurfaceFusion(cfg)
    times = [0.0, 0.002, 0.04, 0.08, 0.082, 0.12]
    rng = np.random.default_rng(3)
    cs = rng.normal(scale=0.01, size=(len(times), 3))
    ns = np.array([[0.0, 0.1 * k, 1.0] for k in range(len(times))])
    ns /= np.linalg.norm(ns, axis=1, keepdims=True)
    ests = [est(t, c, n) for t, c, n in zip(times, cs, ns, strict=True)]
    for e in ests:
        fusion.add(e)
    expected = fit_window(
        np.array(times),
        np.array([e.centroid for e in ests]),
        np.array([e.normal for e in ests]),
        ["a"] * len(times),
        window_s=cfg.window_s,
        half_life_s=cfg.weight_half_life_s,
        weighting="inverse",
        max_degree=1,
        normal_max_degree=0,
        time_resolution_s=0.004,
    )
    assert fusion.fit == expected
    assert (expected.degree, expected.normal_degree, expected.n_times) == (1, 0, 4)


# ----- outputs, arguments ----------------------------------------------------------------------
def test_every_output_field_of_a_valid_and_of_an_empty_fusion() -> None:
    fusion = SurfaceFusion()
    empty = fusion.sample(0.5)
    assert (empty.t, empty.valid, empty.stale, empty.seq) == (0.5, False, False, 1)
    assert (empty.n_samples, empty.degree, empty.cameras) == (0, 0, ())
    assert empty.free_m == 0.0 and empty.free_hip is None
    fusion.add(est(0.5, (0.0, 0.0, 0.25), cam="front"))
    out = fusion.sample(0.53125)
    assert (out.t, out.valid, out.stale, out.reason, out.seq) == (0.53125, True, False, "", 2)
    assert (out.n_samples, out.degree, out.cameras, out.age_s) == (1, 0, ("front",), 0.03125)


def test_sample_times_of_any_real_type_become_floats() -> None:
    fusion = SurfaceFusion()
    fusion.add(est(0.0, (0.0, 0.0, 0.0)))
    a = fusion.sample(1)
    assert a.t == 1.0 and type(a.t) is float
    b = fusion.sample(np.float64(1.5))
    assert b.t == 1.5 and type(b.t) is float
    with pytest.raises(InputError, match=r"^t: expected a number, got 'soon'$"):
        fusion.sample("soon")  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"^t: must be finite"):
        fusion.sample(np.inf)


def test_wrong_types_are_named() -> None:
    with pytest.raises(InputError, match=r"^est: expected a SurfaceEstimate, got tuple$"):
        SurfaceFusion().add((0.0, "a", (0, 0, 0), UP, True))  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"^config: expected a FusionConfig, got dict$"):
        SurfaceFusion({"kp": 1.0})  # type: ignore[arg-type]


def test_integral_gains_build_followers_that_track() -> None:
    cfg = FusionConfig(ki=1000.0, normal_ki=100.0)
    fusion = SurfaceFusion(cfg)
    for k in range(10):
        fusion.add(est(k / 30, (0.2 * k / 30, 0.0, 0.5)))
    out = fusion.sample(9 / 30 + DT)
    assert out.valid and np.isfinite(out.centroid).all()


# ----- free-space proofs -----------------------------------------------------------------------
def test_a_proof_is_reported_until_max_age_with_its_hip() -> None:
    fusion = SurfaceFusion(FusionConfig(max_age_s=0.25, max_extrapolation_s=0.0625))
    assert fusion.add(proof(0.5, 0.125, hip=(0.1, 0.2, 0.3))) is False
    assert fusion.n_invalid == 1
    out = fusion.sample(0.5)
    assert out.free_m == 0.125 and out.free_hip is not None
    np.testing.assert_array_equal(out.free_hip, [0.1, 0.2, 0.3])
    assert not out.valid  # a proof is no surface
    assert fusion.sample(0.75).free_m == 0.125  # exactly max_age_s old: still counts
    late = fusion.sample(0.75 + 1e-9)
    assert late.free_m == 0.0 and late.free_hip is None


def test_only_complete_newest_proofs_count() -> None:
    fusion = SurfaceFusion()
    fusion.add(est(0.0, (0.0, 0.0, 0.0), valid=False, hip=(0.0, 0.0, 1.0)))  # no proof
    out = fusion.sample(0.0)
    assert out.free_m == 0.0 and out.free_hip is None
    fusion.add(est(0.0, (0.0, 0.0, 0.0), valid=False, free_m=0.125))  # no hip: no proof
    assert fusion.sample(0.001).free_m == 0.0
    fusion.add(proof(float("inf"), 0.125))  # no time: no proof
    assert fusion.sample(0.002).free_m == 0.0
    fusion.add(proof(0.01, 0.5, hip=(1.0, 0.0, 0.0)))
    fusion.add(proof(0.005, 0.25, hip=(2.0, 0.0, 0.0)))  # older: does not replace it
    fusion.add(est(0.02, (0.0, 0.0, 0.0), valid=False, hip=(3.0, 0.0, 0.0)))  # no proof
    out = fusion.sample(0.02)
    assert out.free_m == 0.5 and out.free_hip is not None and out.free_hip[0] == 1.0
    fusion.add(proof(0.01, 0.375, hip=(4.0, 0.0, 0.0)))  # same time, later: replaces it
    out = fusion.sample(0.03)
    assert out.free_m == 0.375 and out.free_hip is not None and out.free_hip[0] == 4.0
