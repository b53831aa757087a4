"""Deferrable work of the control loop (:mod:`hapticloud.hardware.control.slack`)."""

from __future__ import annotations

import math

import pytest
from hapticloud.hardware.control.slack import Slack
from hypothesis import given
from hypothesis import strategies as st


def test_unmeasured_work_runs_and_its_cost_is_learnt():
    slack = Slack(3)
    assert slack.expected_s == 0.0
    assert slack.fits(0.0)  # nothing known yet: run it, and learn
    slack.record(400e-6)
    assert slack.expected_s == pytest.approx(400e-6)
    assert slack.fits(500e-6)
    assert slack.deferred == 0


def test_work_that_does_not_fit_waits_at_most_max_defer_ticks():
    slack = Slack(3)
    slack.record(600e-6)
    runs = [slack.fits(100e-6) for _ in range(9)]
    # Put off three times, then run; and again.
    assert runs == [False, False, False, True, False, False, False, True, False]
    assert slack.deferred == 7 and slack.forced == 2
    # Time left again: runs at once, and the wait starts over.
    assert slack.fits(1e-3)
    assert [slack.fits(0.0) for _ in range(4)] == [False, False, False, True]


def test_expected_cost_is_a_quantile_of_the_recent_window():
    slack = Slack(2, window=10, quantile=0.9)
    for _ in range(9):
        slack.record(100e-6)
    slack.record(5e-3)  # one outlier in ten: the 0.9 quantile is the outlier
    assert slack.expected_s == pytest.approx(5e-3)
    for _ in range(10):
        slack.record(100e-6)  # the window has moved past it
    assert slack.expected_s == pytest.approx(100e-6)


def test_nan_time_left_and_bad_costs():
    slack = Slack(1)
    slack.record(200e-6)
    assert not slack.fits(math.nan)  # unknown time left: no time left
    assert slack.fits(math.nan)  # ... but only max_defer times
    for bad in (math.nan, math.inf, -1.0):
        slack.record(bad)
    assert slack.expected_s == pytest.approx(200e-6)


@pytest.mark.parametrize(
    "kwargs", [{"max_defer": -1}, {"max_defer": 1, "window": 0}, {"max_defer": 1, "quantile": 2.0}]
)
def test_bad_parameters_are_refused(kwargs):
    with pytest.raises(ValueError):
        Slack(**kwargs)


@given(
    st.integers(0, 10),
    st.lists(
        st.tuples(st.floats(-1e-3, 2e-3) | st.just(math.nan), st.floats(0, 2e-3)), max_size=200
    ),
)
def test_property_never_more_than_max_defer_in_a_row(max_defer, steps):
    slack = Slack(max_defer)
    in_a_row = 0
    for left, cost in steps:
        if slack.fits(left):
            in_a_row = 0
            slack.record(cost)
        else:
            in_a_row += 1
        assert in_a_row <= max_defer
        assert math.isfinite(slack.expected_s) and slack.expected_s >= 0.0
