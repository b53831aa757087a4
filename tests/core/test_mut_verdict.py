"""The run's verdict pinned down where mutation testing found it loose (docs/testing.md): the
SAFE/UNSAFE boundary, what explains an UNSAFE moment (how long the space was unknown, how old the
estimate was), runs without a truth, the open-loop verdict, the JSON form and the space summary."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hapticloud.core.haptics.unknown import SpaceState, SpaceTransition
from hapticloud.core.studies.verdict import (
    ALLOWED_PENETRATION_M,
    UNSAFE_EXIT_CODE,
    Verdict,
    judge,
    judge_estimates,
    no_truth,
    space_summary,
)

T = np.arange(6) * 0.25  # 0, 0.25, ..., 1.25 s


def test_exactly_the_allowed_penetration_is_still_safe() -> None:
    allowed = 0.25  # exact in binary
    v = judge(T, np.array([0.5, -0.25, 0.0, 0.1, 0.2, 0.3]), allowed_penetration_m=allowed)
    assert v == Verdict(True, -0.25, 0.25, "", allowed)
    assert v.line() == "SAFE: min margin -250.0 mm at t=0.25 s (allowed -250.0 mm)"
    v = judge(T, np.array([0.5, -0.26, 0.0, 0.1, 0.2, 0.3]), allowed_penetration_m=allowed)
    assert v.safe is False and v.exit_code == UNSAFE_EXIT_CODE and v.label == "UNSAFE"


def test_one_sample_is_judged_and_non_finite_samples_are_skipped() -> None:
    v = judge(np.array([2.0]), np.array([0.125]))
    assert v == Verdict(True, 0.125, 2.0, "", ALLOWED_PENETRATION_M)
    v = judge(T, np.array([np.nan, np.inf, 0.5, -np.inf, 0.25, np.nan]))
    assert (v.min_margin_m, v.t_min_s) == (0.25, 1.0)


@pytest.mark.parametrize("margin", [np.zeros(0), np.full(3, np.inf), np.full(2, np.nan)])
def test_no_finite_margin_is_no_truth(margin: np.ndarray) -> None:
    t = np.arange(margin.size, dtype=float)
    v = judge(t, margin, allowed_penetration_m=0.125)
    assert v == Verdict(None, None, None, "no true surface to measure against", 0.125)
    assert v.line() == "NO TRUTH: no true surface to measure against"
    assert v.exit_code == 0 and v.label == "NO TRUTH"


def _unsafe_at(i: int, **kw) -> Verdict:
    margin = np.full(T.size, 0.01)
    margin[i] = -0.5
    return judge(T, margin, **kw)


def test_the_unknown_space_before_the_worst_moment_is_measured_from_its_start() -> None:
    # HOLDING from the first tick (and again at the end, which must not count)
    space = np.array([1, 1, 2, 0, 0, 1], dtype=float)
    v = _unsafe_at(2, space=space)
    assert v.reason == "space stopped for 500 ms"
    assert v.line() == (
        "UNSAFE: min margin -500.0 mm at t=0.50 s (allowed -2.0 mm; reason: space stopped for"
        " 500 ms)"
    )
    # a run that starts after a known tick
    space = np.array([0, 0, 1, 1, 1, 1], dtype=float)
    assert _unsafe_at(5, space=space).reason == "space holding for 750 ms"
    space = np.array([1, 0, 0, 1, 1, 1], dtype=float)
    assert _unsafe_at(5, space=space).reason == "space holding for 500 ms"
    assert _unsafe_at(3, space=space).reason == "space holding for 0 ms"


@pytest.mark.parametrize(
    ("age", "reason"),
    [
        (math.inf, "no valid estimate yet"),
        (-1.0, "no valid estimate yet"),
        (math.nan, "no valid estimate yet"),
        (0.0, "the constraints did not hold (estimate error or too little torque)"),
        (0.1, "the constraints did not hold (estimate error or too little torque)"),
        (0.5, "no valid estimate for 500 ms"),
        (2.5, "no valid estimate for 2500 ms"),
    ],
)
def test_the_age_of_the_estimate_explains_a_known_space(age: float, reason: str) -> None:
    ages = np.full(T.size, 0.01)
    ages[4] = age
    assert _unsafe_at(4, fused_age_s=ages).reason == reason
    # with the space known at that moment, the age still explains it
    known = np.zeros(T.size)
    assert _unsafe_at(4, space=known, fused_age_s=ages).reason == reason


def test_without_space_or_age_the_constraints_are_blamed() -> None:
    assert _unsafe_at(1).reason == (
        "the constraints did not hold (estimate error or too little torque)"
    )


def test_the_line_of_every_kind_of_verdict() -> None:
    assert Verdict(None, None, 1.0, "no truth at all").line() == "NO TRUTH: no truth at all"
    assert Verdict(True, 0.25, None, "half").line() == "SAFE: half"
    v = Verdict(None, 0.375, 1.5, "held 2 times")
    assert v.line() == "NO TRUTH: estimated min margin +375.0 mm at t=1.50 s (held 2 times)"
    v = Verdict(False, -0.5, 3.25, "why", allowed_penetration_m=0.25)
    assert v.line() == "UNSAFE: min margin -500.0 mm at t=3.25 s (allowed -250.0 mm; reason: why)"


def test_to_json_has_every_field_and_no_infinities() -> None:
    v = Verdict(False, -0.5, 3.25, "why", allowed_penetration_m=0.25)
    assert v.to_json() == {
        "verdict": "UNSAFE",
        "safe": False,
        "line": v.line(),
        "min_margin_m": -0.5,
        "t_min_margin_s": 3.25,
        "reason": "why",
        "allowed_penetration_m": 0.25,
    }
    j = Verdict(None, math.inf, -math.inf, "none").to_json()
    assert j["min_margin_m"] is None and j["t_min_margin_s"] is None
    assert j["verdict"] == "NO TRUTH" and j["safe"] is None
    j = Verdict(None, None, None, "none").to_json()
    assert j["min_margin_m"] is None and j["t_min_margin_s"] is None


def test_open_loop_estimates_are_unsafe_only_when_reported_farther() -> None:
    t = np.array([0.0, 0.5, 1.0])
    true = np.array([0.1, 0.1, 0.1])
    closer = judge_estimates(t, np.array([0.05, 0.0, 0.1]), true, allowed_m=0.125)
    assert closer == Verdict(True, 0.0, 1.0, "", 0.125)
    farther = judge_estimates(t, np.array([0.1, 0.5, 0.1]), true, allowed_m=0.125)
    assert farther == Verdict(
        False, pytest.approx(-0.4), 0.5, "an estimate reported the surface farther", 0.125
    )
    # exactly the allowed amount farther is still safe
    edge = judge_estimates(t, np.array([0.1, 0.25, 0.1]), np.full(3, 0.125), allowed_m=0.125)
    assert edge.safe is True and edge.min_margin_m == -0.125
    nothing = judge_estimates(t, np.full(3, np.nan), true, allowed_m=0.125)
    assert nothing == Verdict(None, None, None, "no valid estimate to judge", 0.125)
    default = judge_estimates(t, np.array([0.1, 0.103, 0.1]), true)
    assert default.safe is False and default.allowed_penetration_m == ALLOWED_PENETRATION_M
    assert judge_estimates([0.0], [0.5], [0.5]).safe is True  # lists are taken too


def test_no_truth_lists_the_events_or_says_there_were_none() -> None:
    v = no_truth(0.25, 1.5, ["held 2 times", "stopped once"])
    assert v == Verdict(None, 0.25, 1.5, "held 2 times; stopped once")
    assert v.line() == (
        "NO TRUTH: estimated min margin +250.0 mm at t=1.50 s (held 2 times; stopped once)"
    )
    assert no_truth(None, None, []) == Verdict(None, None, None, "no hold, no stop")


def test_space_summary_fractions_longest_unknown_and_transitions() -> None:
    space = np.array([0, 1, 1, 2, 0, 0, 1, 0], dtype=float)
    tr = [
        SpaceTransition(0.25, SpaceState.HOLDING, "lost"),
        SpaceTransition(0.5, SpaceState.KNOWN, ""),
    ]
    s = space_summary(np.arange(8) * 0.125, space, tr, 0.125)
    assert s["fraction"] == {"known": 0.5, "holding": 0.375, "stopped": 0.125}
    assert s["longest_unknown_s"] == 0.375
    assert s["transitions"] == [[0.25, "holding", "lost"], [0.5, "known", ""]]
    empty = space_summary(np.zeros(0), np.zeros(0), [], 0.001)
    assert empty["fraction"] == {"known": 0.0, "holding": 0.0, "stopped": 0.0}
    assert empty["longest_unknown_s"] == 0.0 and empty["transitions"] == []
    tail = space_summary(np.arange(4) * 0.5, np.array([1.0, 0.0, 2.0, 2.0]), [], 0.5)
    assert tail["longest_unknown_s"] == 1.0
    head = space_summary(np.arange(4) * 0.5, np.array([2.0, 2.0, 2.0, 0.0]), [], 0.5)
    assert head["longest_unknown_s"] == 1.5
    one = space_summary(np.zeros(1), np.array([1.0]), [], 0.5)
    assert one["fraction"] == {"known": 0.0, "holding": 1.0, "stopped": 0.0}
    assert one["longest_unknown_s"] == 0.5
