"""``hapticloud app --enable``: the session is enabled once, when it is READY, its surface known
and its watchdogs quiet, not before its cameras' first estimates reached the loop."""

from __future__ import annotations

import math

from hapticloud.hardware.control.messages import ControlSnapshot
from hapticloud.hardware.live.session import Session, SessionPhase, ready_to_enable


def _snap(seq: int, state: str, space: str, reaction: str) -> ControlSnapshot:
    zeros6 = (0.0,) * 6
    return ControlSnapshot(
        seq, seq, 0.01 * seq, state, reaction, "", "", zeros6, zeros6, zeros6, (0.0, 0.0, 1.0),
        (0.0, 0.0, 0.0), math.nan, math.nan, 0.0, False, math.inf, (), 300.0, 300.0, 800.0, 0,
        0, 0.4, (), space,
    )  # fmt: skip


class _Process:
    """What :meth:`Session.poll` reads of a control process: its snapshots, one batch a call."""

    alive = True

    def __init__(self, batches: list[list[ControlSnapshot]]) -> None:
        self.batches = batches

    def snapshots(self) -> list[ControlSnapshot]:
        return self.batches.pop(0) if self.batches else []


def test_enable_waits_for_the_surface_and_quiet_watchdogs_then_enables_once() -> None:
    steps = [
        ("starting", "stopped", "NONE"),
        ("ready", "stopped", "NONE"),  # no estimate has reached the loop yet
        ("ready", "known", "HOLD_SURFACE"),  # a camera still silent
        ("ready", "known", "NONE"),  # now
        ("ready", "known", "NONE"),
    ]
    session = Session("demo", enable_when_ready=True)
    session._cp = _Process([[_snap(i, *step)] for i, step in enumerate(steps)])
    session._phase = SessionPhase.RUNNING
    enabled_at: list[int] = []
    poll = [0]
    session.enable = lambda: enabled_at.append(poll[0]) or True  # type: ignore[method-assign]
    for i in range(len(steps)):
        poll[0] = i
        session.poll()
    assert enabled_at == [3]  # at the first READY snapshot with the surface known, once
    assert [ready_to_enable(_snap(0, *step)) for step in steps] == [
        False,
        False,
        False,
        True,
        True,
    ]
