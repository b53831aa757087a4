"""The velocity constraint pinned down where mutation testing found it loose (docs/testing.md):
the ramp's slope with v_max - v_min != 1, the ramp's edges, the sign of the J-dot q-dot term, the
activation boundary, the shared haptic state and the rows' name."""

from __future__ import annotations

import numpy as np
import pytest
from hapticloud.core.errors import ConfigError
from hapticloud.core.haptics import (
    HapticState,
    VelocityConstraint,
    VelocityConstraintConfig,
    approach_speed_bound,
)
from hapticloud.core.haptics.velocity import MIN_RAMP_WIDTH_M

DT = 1.0 / 800.0


def _haptic(d_proj: float, *, jdc_qd: float = 0.0, d_dot: float = 0.0, n: int = 3) -> HapticState:
    """A haptic state with exact numbers (no robot, no rounding in d_proj)."""
    J_c = np.arange(1.0, n + 1.0)
    return HapticState(
        d_proj=d_proj,
        J_c=J_c,
        Jdc_qd=jdc_qd,
        d_dot_robot=d_dot,
        d_dot_surface=0.0,
        qd=np.zeros(n),
        normal=np.array([0.0, 0.0, 1.0]),
        surface_velocity=np.zeros(3),
    )


def test_the_ramp_has_the_slope_of_its_two_speeds() -> None:
    # v_max - v_min = 0.4 (not 1): halfway up the ramp is halfway between the speeds.
    args = {"v_min_mps": 0.05, "v_max_mps": 0.45, "d_offset_m": 0.01, "d_width_m": 0.1}
    assert approach_speed_bound(0.06, **args) == pytest.approx(0.25)
    assert approach_speed_bound(0.035, **args) == pytest.approx(0.15)
    # and with a ramp steeper than 1 (m/s per ramp width)
    args = {"v_min_mps": 0.2, "v_max_mps": 3.2, "d_offset_m": 0.0, "d_width_m": 0.2}
    assert approach_speed_bound(0.05, **args) == pytest.approx(0.95)


def test_a_ramp_exactly_as_wide_as_the_step_limit_is_still_a_ramp() -> None:
    w = MIN_RAMP_WIDTH_M
    args = {"v_min_mps": 0.1, "v_max_mps": 0.9, "d_offset_m": 0.0, "d_width_m": w}
    assert approach_speed_bound(0.5 * w, **args) == pytest.approx(0.5)
    # narrower is a step at d_offset
    args["d_width_m"] = 0.5 * w
    assert approach_speed_bound(0.25 * w, **args) == 0.9


def test_equal_speeds_and_activation_at_the_ramp_end_are_valid_configs() -> None:
    cfg = VelocityConstraintConfig(v_min_mps=0.3, v_max_mps=0.3)
    assert cfg.bound(0.0) == cfg.bound(0.05) == cfg.bound(1.0) == 0.3
    # 0.25 + 0.5 is exactly 0.75 in binary: rows appear exactly where the ramp ends
    cfg = VelocityConstraintConfig(d_offset_m=0.25, d_width_m=0.5, activation_distance_m=0.75)
    assert cfg.activation_distance_m == 0.75
    with pytest.raises(ConfigError, match=r"^activation_distance_m"):
        VelocityConstraintConfig(d_offset_m=0.25, d_width_m=0.5, activation_distance_m=0.749)


def test_the_jdot_qd_term_enters_h_with_its_sign() -> None:
    cfg = VelocityConstraintConfig(kv=4.0)
    con = VelocityConstraint(cfg)
    base = con.rows(None, None, DT, haptic=_haptic(0.05)).h[0]
    # d_ddot = J_c qdd + Jdc_qd <= ...: a drift away from the surface (Jdc_qd > 0) lets the
    # controller approach harder, so h grows by exactly Jdc_qd.
    up = con.rows(None, None, DT, haptic=_haptic(0.05, jdc_qd=2.0)).h[0]
    down = con.rows(None, None, DT, haptic=_haptic(0.05, jdc_qd=-3.0)).h[0]
    assert up - base == pytest.approx(2.0)
    assert down - base == pytest.approx(-3.0)
    assert base == pytest.approx(cfg.bound(0.05) / (cfg.kv * DT))


def test_rows_exactly_at_the_activation_distance() -> None:
    cfg = VelocityConstraintConfig()
    con = VelocityConstraint(cfg)
    at = con.rows(None, None, DT, haptic=_haptic(cfg.activation_distance_m))
    beyond = con.rows(None, None, DT, haptic=_haptic(np.nextafter(cfg.activation_distance_m, 1)))
    assert at.G.shape == (1, 6)
    np.testing.assert_array_equal(at.G[0, :3], -np.arange(1.0, 4.0))
    assert beyond.G.shape == (0, 6)


def test_a_shared_haptic_state_is_used_without_reading_state_or_surface() -> None:
    rows = VelocityConstraint().rows(None, None, DT, haptic=_haptic(0.02, d_dot=-0.1))
    assert rows.G.shape == (1, 6)
    assert np.isfinite(rows.h).all()


def test_rows_carry_the_constraint_name_active_or_not() -> None:
    for name in (VelocityConstraint.default_name, "wall_3"):
        con = VelocityConstraint(name=name)
        assert con.name == name
        assert con.rows(None, None, DT, haptic=_haptic(0.01)).name == name
        assert con.rows(None, None, DT, haptic=_haptic(1.0)).name == name
    assert VelocityConstraint().rows(None, None, DT, haptic=_haptic(1.0)).name == "haptic_velocity"
