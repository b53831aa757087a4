"""The haptic quantities pinned down where mutation testing found them loose (docs/testing.md):
every field of the haptic state, the overflow guard on the sum of the rates, the boundaries of the
normal's length and of the Jacobian's width, the radius 0 that is allowed, and each error naming
its input exactly (the project's rule: bad input says which field)."""

from __future__ import annotations

from fractions import Fraction
from types import SimpleNamespace

import numpy as np
import pytest
from hapticloud.core.errors import InputError
from hapticloud.core.haptics import (
    HipState,
    SurfacePoint,
    constraint_jacobian,
    d_proj,
    haptic_state,
)
from hapticloud.core.haptics.distance import surface_of

R_HIP = 0.04


def _hip(jacobian=None, *, qd=None, jdot_qd=(0.0, 0.0, 0.0), radius=R_HIP, position=(0, 0, 0)):
    jac = np.array([[1.0, 0.0], [0.0, 2.0], [3.0, 4.0]]) if jacobian is None else jacobian
    jac = np.asarray(jac, dtype=float)
    n = jac.shape[1]
    return HipState(
        np.asarray(position, dtype=float),
        np.zeros(n) if qd is None else np.asarray(qd, dtype=float),
        jac,
        np.asarray(jdot_qd, dtype=float),
        np.eye(n),
        np.zeros(n),
        radius,
    )


UP = SurfacePoint(np.array([0.0, 0.0, -0.1]), np.array([0.0, 0.0, 1.0]))


def test_every_field_of_the_haptic_state() -> None:
    hip = _hip(qd=[0.5, -0.25], jdot_qd=[0.1, 0.2, 0.3])
    surface = SurfacePoint(
        np.array([0.0, 0.0, -0.1]), np.array([0.0, 0.0, 2.0]), np.array([0.2, 0.0, -0.5])
    )
    hs = haptic_state(hip, surface)
    assert hs.d_proj == pytest.approx(0.1 - R_HIP)
    np.testing.assert_array_equal(hs.normal, [0.0, 0.0, 1.0])  # normalised
    np.testing.assert_array_equal(hs.J_c, [3.0, 4.0])
    assert hs.Jdc_qd == pytest.approx(0.3)
    assert hs.d_dot_robot == pytest.approx(3.0 * 0.5 - 4.0 * 0.25)
    assert hs.d_dot_surface == pytest.approx(0.5)  # moving away: the distance grows
    np.testing.assert_array_equal(hs.qd, [0.5, -0.25])
    np.testing.assert_array_equal(hs.surface_velocity, [0.2, 0.0, -0.5])
    assert hs.n_joints == 2 and hip.n_joints == 2


@pytest.mark.parametrize(
    ("jdot_z", "qd", "vz"),
    [
        (0.0, 1e154, -1e308),  # robot rate + surface rate overflow together
        (1e308, 1e154, 0.0),  # J-dot q-dot + robot rate overflow together
    ],
)
def test_rates_whose_sum_overflows_are_refused(jdot_z: float, qd: float, vz: float) -> None:
    # Each rate is finite, but the rows add them: inf would reach the controller.
    hip = _hip([[0.0], [0.0], [1e154]], qd=[qd], jdot_qd=[0.0, 0.0, jdot_z])
    surface = SurfacePoint(np.zeros(3), np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, vz]))
    with pytest.raises(
        InputError, match=r"^haptic_state: inputs too large, the distance or its rates overflow$"
    ):
        haptic_state(hip, surface)


def test_a_normal_of_length_1e_12_is_refused_and_just_above_is_accepted() -> None:
    hip = _hip()
    with pytest.raises(InputError, match=r"^surface\.normal: must be a non-zero direction"):
        haptic_state(hip, UP._replace(normal=np.array([1e-12, 0.0, 0.0])))
    hs = haptic_state(hip, UP._replace(normal=np.array([0.0, 0.0, 1.0000000000000002e-12])))
    np.testing.assert_array_equal(hs.normal, [0.0, 0.0, 1.0])


@pytest.mark.parametrize("radius", [0.0, R_HIP])
def test_a_normal_whose_square_overflows_is_refused_not_zeroed(radius: float) -> None:
    with (
        np.errstate(over="ignore"),
        pytest.raises(InputError, match=r"^surface\.normal: must be a finite non-zero direction$"),
    ):
        haptic_state(_hip(radius=radius), UP._replace(normal=np.array([0.0, 0.0, 1e200])))


@pytest.mark.parametrize("radius", [0.0, R_HIP])
def test_inconsistent_shapes_that_each_validate_are_refused_as_such(radius: float) -> None:
    # A column centroid passes the per-field check (3 numbers) but not the tick's fast path.
    surface = UP._replace(centroid=np.zeros((3, 1)))
    with pytest.raises(InputError, match=r"^haptic_state: inputs of inconsistent shapes$"):
        haptic_state(_hip(radius=radius), surface)


def test_the_jacobian_needs_one_column_or_more() -> None:
    n = np.array([0.0, 0.0, 1.0])
    np.testing.assert_array_equal(constraint_jacobian(n, [[1.0], [2.0], [3.0]]), [3.0])
    with pytest.raises(InputError, match=r"^jacobian: expected shape \(3, n\), got \(3, 0\)$"):
        constraint_jacobian(n, np.zeros((3, 0)))
    with pytest.raises(InputError, match=r"^jacobian: expected shape \(3, n\), got \(2, 3\)$"):
        constraint_jacobian(n, np.zeros((2, 3)))
    with pytest.raises(InputError, match=r"^jacobian: must be finite$"):
        constraint_jacobian(n, [[1.0], [np.inf], [0.0]])
    hs = haptic_state(_hip([[1.0], [0.0], [2.0]], qd=[1.0]), UP)
    assert hs.n_joints == 1 and hs.d_dot_robot == 2.0
    with pytest.raises(InputError, match=r"^jacobian: expected shape \(3, n\), got \(3, 0\)$"):
        haptic_state(_hip(np.zeros((3, 0)), qd=np.zeros(0)), UP)


def test_text_instead_of_numbers_is_named_not_a_type_error() -> None:
    with pytest.raises(InputError, match=r"^surface\.centroid: expected 3 real numbers"):
        haptic_state(_hip(), UP._replace(centroid=np.array(["a", "b", "c"])))
    with pytest.raises(InputError, match=r"^hip\.radius_m: expected a number"):
        haptic_state(_hip(radius="four"), UP)  # type: ignore[arg-type]


def test_any_real_numbers_are_taken_as_floats() -> None:
    # e.g. exact rationals from a symbolic model: converted, not kept as Python objects
    third, half = Fraction(1, 3), Fraction(1, 2)
    jac = [[third, Fraction(0)], [Fraction(0), half], [Fraction(3), Fraction(4)]]
    np.testing.assert_allclose(constraint_jacobian([0, 0, 1], jac), [3.0, 4.0])
    np.testing.assert_allclose(constraint_jacobian([1, 0, 0], jac), [1 / 3, 0.0])
    hip = HipState(
        [Fraction(0)] * 3, [half, third], jac, [Fraction(0)] * 3, np.eye(2), np.zeros(2), half
    )
    surface = SimpleNamespace(
        centroid=[Fraction(0), Fraction(0), Fraction(-1)],
        normal=[Fraction(0), Fraction(0), Fraction(2)],
        velocity=[Fraction(0), Fraction(0), Fraction(1)],
    )
    hs = haptic_state(hip, surface)
    assert hs.d_proj == pytest.approx(0.5)
    assert hs.d_dot_robot == pytest.approx(3.0 * 0.5 + 4.0 / 3.0)
    assert hs.d_dot_surface == pytest.approx(-1.0)
    assert hs.qd.dtype == np.float64 and hs.surface_velocity.dtype == np.float64


def test_each_bad_input_is_named_exactly() -> None:
    hip = _hip()
    cases = [
        (hip, UP._replace(centroid=np.array([np.nan, 0, 0])), r"^surface\.centroid: must be"),
        (hip, UP._replace(normal=np.zeros(3)), r"^surface\.normal: must be a non-zero direction"),
        (hip, UP._replace(velocity=np.array([0, np.inf, 0])), r"^surface\.velocity: must be"),
        (hip._replace(position=np.array([0, np.nan, 0])), UP, r"^hip\.position: must be finite"),
        (hip._replace(jdot_qd=np.array([np.inf, 0, 0])), UP, r"^hip\.jdot_qd: must be finite"),
        (hip._replace(jdot_qd=np.zeros(4)), UP, r"^hip\.jdot_qd: expected shape \(3,\)"),
        (hip._replace(radius_m=-0.5), UP, r"^hip\.radius_m = -0\.5: must be >= 0$"),
        (hip._replace(radius_m=np.nan), UP, r"^hip\.radius_m: must be finite"),
    ]
    for state, surface, pattern in cases:
        with pytest.raises(InputError, match=pattern):
            haptic_state(state, surface)
    with pytest.raises(
        InputError, match=r"^surface: expected an object with centroid and normal, got int$"
    ):
        haptic_state(hip, 3)


def test_d_proj_and_constraint_jacobian_name_their_arguments() -> None:
    with pytest.raises(InputError, match=r"^centroid: must be finite"):
        d_proj([np.nan, 0, 0], [0, 0, 1], [0, 0, 0], R_HIP)
    with pytest.raises(InputError, match=r"^r_hip_m: expected a number"):
        d_proj([0, 0, 0], [0, 0, 1], [0, 0, 0], "r")  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"^r_hip_m = -0\.01: must be >= 0$"):
        d_proj([0, 0, 0], [0, 0, 1], [0, 0, 0], -0.01)
    assert d_proj([0, 0, 0], [0, 0, 1], [0, 0, 0.25], 0.0) == 0.25  # radius 0 is allowed
    with pytest.raises(InputError, match=r"^normal: must be a non-zero direction"):
        constraint_jacobian([0, 0, 0], np.ones((3, 2)))


def test_surface_of_normalises_and_defaults_a_missing_velocity_to_zero() -> None:
    bare = SimpleNamespace(centroid=[0.0, 1.0, 2.0], normal=[0.0, 3.0, 4.0])
    c, n, v = surface_of(bare)
    np.testing.assert_array_equal(c, [0.0, 1.0, 2.0])
    np.testing.assert_allclose(n, [0.0, 0.6, 0.8])
    np.testing.assert_array_equal(v, [0.0, 0.0, 0.0])
    _, _, v = surface_of(SimpleNamespace(centroid=c, normal=n, velocity=[1.0, 2.0, 3.0]))
    np.testing.assert_array_equal(v, [1.0, 2.0, 3.0])
    for field, bad, pattern in (
        ("centroid", [0.0, np.nan, 0.0], r"^surface\.centroid: must be finite"),
        ("normal", [0.0, 0.0, 0.0], r"^surface\.normal: must be a non-zero direction"),
        ("velocity", [np.inf, 0.0, 0.0], r"^surface\.velocity: must be finite"),
    ):
        fields = {"centroid": c, "normal": n, "velocity": v, field: bad}
        with pytest.raises(InputError, match=pattern):
            surface_of(SimpleNamespace(**fields))


class _Model:
    """What HipState.from_model reads, with fixed numbers."""

    qd = np.array([0.1, 0.2])

    def hip_position(self):
        return np.array([1.0, 2.0, 3.0])

    def hip_jacobian(self):
        return np.ones((3, 2))

    def hip_jdot_qd(self):
        return np.array([0.0, 0.0, 9.0])

    def mass_matrix(self):
        return 2.0 * np.eye(2)

    def nonlinear_effects(self):
        return np.array([5.0, 6.0])


def test_hip_state_from_model_reads_every_field_and_allows_radius_zero() -> None:
    hip = HipState.from_model(_Model(), 0.0)
    assert hip.radius_m == 0.0
    np.testing.assert_array_equal(hip.position, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(hip.qd, [0.1, 0.2])
    np.testing.assert_array_equal(hip.jdot_qd, [0.0, 0.0, 9.0])
    np.testing.assert_array_equal(hip.mass_matrix, 2.0 * np.eye(2))
    np.testing.assert_array_equal(hip.nonlinear_effects, [5.0, 6.0])
    with pytest.raises(InputError, match=r"^radius_m = -0\.01: must be >= 0$"):
        HipState.from_model(_Model(), -0.01)
    with pytest.raises(InputError, match=r"^radius_m: expected a number"):
        HipState.from_model(_Model(), "big")  # type: ignore[arg-type]
