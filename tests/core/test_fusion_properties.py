"""Property tests of core/fusion: invariances, normals in every direction, bounded followers."""

from __future__ import annotations

import itertools
import math

import numpy as np
from hapticloud.core.errors import ConfigError
from hapticloud.core.fusion import (
    FusionConfig,
    NormalFollower,
    PidGains,
    PointFollower,
    SurfaceFusion,
    gain_problem,
    iteration_matrix,
)
from hapticloud.core.perception.estimate import SurfaceEstimate
from hypothesis import assume, given, settings
from hypothesis import strategies as st

DT = 1.0 / 800.0
FAST = settings(max_examples=40, deadline=None)

finite = st.floats(-1.0, 1.0, allow_nan=False)
AXES = [tuple(float(v) for v in row) for row in np.vstack([np.eye(3), -np.eye(3)])]


@st.composite
def unit_vectors(draw):
    """Any direction; the poles, the axes and the ±x azimuth wrap are drawn on purpose."""
    if draw(st.booleans()):
        return np.array(draw(st.sampled_from(AXES)))
    v = np.array([draw(finite), draw(finite), draw(finite)])
    assume(np.linalg.norm(v) > 1e-3)
    return v / np.linalg.norm(v)


def signed_permutations():
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[range(3), perm] = signs
            yield m


SIGNED_PERMS = list(signed_permutations())


def scenario(
    t0,
    c_of,
    n_of,
    *,
    T=0.35,
    cfg=None,
    cams=(("a", 0.0), ("b", 0.013)),
    seed=0,
    noise=0.001,
    m=None,
    shift=0.0,
):
    """Estimates at 30 Hz per camera (with noise; then mapped by ``m``, ``shift`` if given),
    samples at 800 Hz; the list of results."""
    fusion = SurfaceFusion(cfg or FusionConfig())
    rng = np.random.default_rng(seed)
    arrivals = sorted((off + k / 30.0, cam) for cam, off in cams for k in range(int(T * 30) + 1))
    out, i = [], 0
    for k in range(int(T * 800)):
        ts = k / 800.0
        while i < len(arrivals) and arrivals[i][0] <= ts:
            te, cam = arrivals[i]
            c = np.asarray(c_of(te)) + rng.normal(0.0, noise, 3)
            n = n_of(te)
            if m is not None:
                c, n = m @ c + shift, m @ n
            fusion.add(SurfaceEstimate(t0 + te, cam, c, n, True))
            i += 1
        out.append(fusion.sample(t0 + ts))
    return out


def rodrigues(axis, angle):
    k = np.asarray(axis, float)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


# ----- invariances of the whole pipeline -------------------------------------------------------
@FAST
@given(
    offset=st.floats(1.0, 2.0e9),
    v=st.tuples(finite, finite, finite),
    acc=st.tuples(finite, finite, finite),
    n0=unit_vectors(),
    axis=unit_vectors(),
    rate=st.floats(-2.0, 2.0),
    seed=st.integers(0, 2**16),
)
def test_epoch_timestamps_give_the_same_result_as_times_near_zero(
    offset, v, acc, n0, axis, rate, seed
) -> None:
    v, acc = 0.5 * np.array(v), np.array(acc)  # up to ~0.9 m/s, 1.7 m/s²

    def c_of(t):
        return v * t + 0.5 * acc * t * t

    def n_of(t):
        return rodrigues(axis, rate * t) @ n0

    near = scenario(0.0, c_of, n_of, seed=seed)
    far = scenario(offset, c_of, n_of, seed=seed)
    for a, b in zip(near, far, strict=True):
        assert a.valid == b.valid and a.degree == b.degree
        assert np.abs(a.centroid - b.centroid).max() < 1e-6
        assert np.abs(a.normal - b.normal).max() < 1e-6


@FAST
@given(
    m=st.sampled_from(SIGNED_PERMS),
    shift=st.tuples(*[st.floats(-10, 10)] * 3),
    n0=unit_vectors(),
    seed=st.integers(0, 2**16),
)
def test_fused_surface_moves_with_the_frame(m, shift, n0, seed) -> None:
    """Rotating/mirroring the world by axis maps and shifting it does the same to the output
    (exactly those maps commute with the per-coordinate PID; the regression and the normal
    follower are equivariant under every rotation)."""
    shift = np.array(shift)

    def c_of(t):
        return np.array([0.3 * t, -0.2 * t * t, 0.1])

    def n_of(t):
        return rodrigues((0, 1, 0), 0.5 * t) @ n0

    base = scenario(0.0, c_of, n_of, seed=seed)
    moved = scenario(0.0, c_of, n_of, seed=seed, m=m, shift=shift)
    for a, b in zip(base, moved, strict=True):
        np.testing.assert_allclose(m @ a.centroid + shift, b.centroid, atol=1e-9)
        np.testing.assert_allclose(m @ a.normal, b.normal, atol=1e-9)
        np.testing.assert_allclose(m @ a.velocity, b.velocity, atol=1e-7)


@FAST
@given(rot_axis=unit_vectors(), rot=st.floats(-math.pi, math.pi), n0=unit_vectors())
def test_regression_target_is_rotation_equivariant(rot_axis, rot, n0) -> None:
    R = rodrigues(rot_axis, rot)

    def c_of(t):
        return np.array([0.3 * t, -0.2 * t * t, 0.1])

    def n_of(t):
        return rodrigues((0, 1, 0), 0.5 * t) @ n0

    base = scenario(0.0, c_of, n_of, T=0.2)
    turned = scenario(0.0, c_of, n_of, T=0.2, m=R)
    for a, b in zip(base, turned, strict=True):
        np.testing.assert_allclose(R @ a.target_centroid, b.target_centroid, atol=1e-9)
        np.testing.assert_allclose(R @ a.target_normal, b.target_normal, atol=1e-9)
        np.testing.assert_allclose(R @ a.normal, b.normal, atol=1e-9)


@FAST
@given(n=unit_vectors(), c=st.tuples(finite, finite, finite), t0=st.floats(0.0, 2e9))
def test_a_constant_normal_in_any_direction_is_returned_unchanged(n, c, t0) -> None:
    out = scenario(t0, lambda t: np.array(c), lambda t: n, T=0.2, noise=0.0)
    assert all(o.valid for o in out)
    for o in out:
        assert np.abs(o.normal - n).max() < 1e-12
        assert np.abs(o.target_normal - n).max() < 1e-12


@FAST
@given(n0=unit_vectors(), toward=unit_vectors(), rate=st.floats(-3.0, 3.0))
def test_a_normal_turning_anywhere_at_constant_rate_is_tracked(n0, toward, rate) -> None:
    """Great-circle turns through the poles and across the azimuth wrap: no singular place."""
    b = toward - np.dot(toward, n0) * n0
    assume(np.linalg.norm(b) > 1e-3)
    b /= np.linalg.norm(b)

    def n_of(t):
        return math.cos(rate * t) * n0 + math.sin(rate * t) * b

    out = scenario(0.0, lambda t: np.zeros(3), n_of, T=0.6, noise=0.0)
    for o in out[int(0.02 * 800) :]:  # two distinct times: the linear normal fit is exact
        assert math.acos(min(1.0, float(np.dot(o.target_normal, n_of(o.t))))) < 1e-6
    last = out[-1]
    assert abs(np.linalg.norm(last.normal) - 1.0) < 1e-12
    assert math.acos(min(1.0, float(np.dot(last.normal, n_of(last.t))))) < 1e-4


# ----- followers ------------------------------------------------------------------------------
# kp, kd and ki as a fraction of its Routh-Hurwitz bound kp * kd (0 = no integral).
gains = st.tuples(
    st.floats(1e-3, 1e6),
    st.floats(1e-3, 1e4),
    st.one_of(st.just(0.0), st.floats(1e-3, 0.999)),
    st.floats(0.0, 1e3),
).map(lambda g: PidGains.make(g[0], g[2] * g[0] * g[1], g[1], g[3]))
dts = st.one_of(st.sampled_from([0.0, -1e-3, 1e-12, 1e-9, DT, 0.05, 10.0]), st.floats(-0.01, 1.0))


@settings(max_examples=80, deadline=None)
@given(g=gains, dt=st.floats(1e-6, 100.0))
def test_backward_euler_follower_is_stable_for_every_accepted_gain_and_dt(g, dt) -> None:
    assert gain_problem(g.kp, g.ki, g.kd) == ""
    m = np.array(iteration_matrix(g, dt))
    # With ki > 0 the integral pole sits just inside 1 (as close as dt * ki / kp); with ki = 0
    # the integral is not fed back (its clamp is 0), so the (e, w) block alone must contract.
    assert max(abs(np.linalg.eigvals(m))) <= 1.0 + 1e-9
    if g.ki == 0.0:
        assert max(abs(np.linalg.eigvals(m[:2, :2]))) < 1.0


@settings(max_examples=80, deadline=None)
@given(kp=st.floats(0.0, 1e6), ki=st.floats(0.0, 1e8), kd=st.floats(0.0, 1e4))
def test_config_accepts_exactly_the_stable_gains(kp, ki, kd) -> None:
    ok = gain_problem(kp, ki, kd) == ""
    try:
        FusionConfig(kp=kp, ki=ki, kd=kd)
    except ConfigError as err:
        assert not ok and any(name in str(err) for name in ("kp", "ki", "kd"))
    else:
        assert ok and ki < kp * kd


@settings(max_examples=60, deadline=None)
@given(
    g=gains,
    start=st.tuples(finite, finite, finite),
    steps=st.lists(st.tuples(st.tuples(finite, finite, finite), dts), min_size=1, max_size=60),
)
def test_point_follower_never_leaves_the_span_of_its_inputs(g, start, steps) -> None:
    fol = PointFollower(g)
    fol.reset(start)
    lo = hi = np.array(start)
    for target, dt in steps:
        lo, hi = np.minimum(lo, target), np.maximum(hi, target)
        y = np.array(fol.step(target, dt))
        assert np.isfinite(y).all()
        assert np.all(y >= lo - 1e-12) and np.all(y <= hi + 1e-12)


@settings(max_examples=60, deadline=None)
@given(
    g=gains,
    start=unit_vectors(),
    target=unit_vectors(),
    max_angle=st.floats(1e-4, math.pi),
    dt_list=st.lists(dts, min_size=1, max_size=60),
)
def test_normal_follower_stays_unit_and_never_overshoots(
    g, start, target, max_angle, dt_list
) -> None:
    fol = NormalFollower(g)
    fol.reset(tuple(start))
    prev = np.array(start)
    err = math.pi
    for dt in dt_list:
        n = np.array(fol.step(tuple(target), dt, max_angle=max_angle))
        assert np.isfinite(n).all() and abs(np.linalg.norm(n) - 1.0) < 1e-12
        turn = math.atan2(np.linalg.norm(np.cross(prev, n)), float(np.dot(prev, n)))
        assert turn <= max_angle + 1e-9
        e = math.atan2(np.linalg.norm(np.cross(n, target)), float(np.dot(n, target)))
        assert e <= err + 1e-9  # the angle to a fixed target never grows
        prev, err = n, e


# ----- arbitrary streams ----------------------------------------------------------------------
event = st.one_of(
    st.tuples(
        st.just("add"),
        st.floats(-0.05, 0.3),  # time step from the previous estimate (may go back)
        st.sampled_from(["a", "b", "c"]),
        st.tuples(finite, finite, finite),
        unit_vectors(),
        st.booleans(),
    ),
    st.tuples(st.just("sample"), st.sampled_from([0.0, -1e-3, 1e-9, DT, DT, DT, 0.02, 0.3])),
)


@settings(max_examples=60, deadline=None)
@given(events=st.lists(event, min_size=1, max_size=80), t0=st.sampled_from([0.0, 1.7e9]))
def test_any_stream_gives_finite_flagged_output(events, t0) -> None:
    cfg = FusionConfig()
    fusion = SurfaceFusion(cfg)
    t_est = t_s = t0
    for ev in events:
        if ev[0] == "add":
            _, step, cam, c, n, valid = ev
            t_est += step
            fusion.add(SurfaceEstimate(t_est, cam, c, n, valid))
            continue
        t_s += ev[1]
        out = fusion.sample(t_s)
        for v in (out.centroid, out.normal, out.velocity, out.target_centroid, out.target_normal):
            assert v.shape == (3,) and np.isfinite(v).all()
        assert abs(np.linalg.norm(out.normal) - 1.0) < 1e-9
        assert abs(np.linalg.norm(out.target_normal) - 1.0) < 1e-9
        assert not (out.valid and out.stale)
        if out.valid:
            assert out.age_s <= cfg.max_age_s and out.n_samples >= 1 and out.reason[:5] != "stale"
        if out.stale:
            assert "stale" in out.reason
