"""Work the loop may put off: run it in what is left of the period, or a few ticks later.

After a tick's command is out, the loop still has work that no torque depends on: adding the
camera estimates that arrived to the fusion (a refit, ~0.2-0.9 ms) and publishing a snapshot for
the GUI (~0.05-0.3 ms). Done in a period whose tick ran long, either pushes the body past the
next deadline: a miss that nothing needed. :class:`Slack` decides, each time such work is due,
whether its recent cost fits in the time left, and otherwise puts it off to a later tick, at most
``max_defer`` ticks in a row (then it runs whatever is left: estimates must not age and the
watchdogs must see them).

Pure bookkeeping: the caller passes the time left and records the cost; no clock here.
"""

from __future__ import annotations

import math
from collections import deque

__all__ = ["Slack"]


class Slack:
    """When a piece of deferrable work runs (one per kind of work).

    Parameters
    ----------
    max_defer
        Ticks in a row the work may be put off; the next time it is due it runs.
    window
        Recent costs kept; the work is expected to cost their ``quantile``.
    quantile
        Quantile of the recent costs taken as the expected cost (0.9: a rare outlier does not
        hold the work back for a whole window).
    """

    def __init__(self, max_defer: int, *, window: int = 64, quantile: float = 0.9) -> None:
        if max_defer < 0:
            raise ValueError(f"max_defer = {max_defer}: must be >= 0")
        if not 0.0 <= quantile <= 1.0:
            raise ValueError(f"quantile = {quantile}: must be in [0, 1]")
        if window < 1:
            raise ValueError(f"window = {window}: must be >= 1")
        self.max_defer = int(max_defer)
        self._costs: deque[float] = deque(maxlen=int(window))
        self._quantile = float(quantile)
        self._expected = 0.0  # nothing measured yet: run it and learn its cost
        self._waited = 0
        self.deferred = 0
        """Times the work was put off."""
        self.forced = 0
        """Times it ran after ``max_defer`` deferrals although it did not fit."""

    @property
    def expected_s(self) -> float:
        """The cost the work is expected to take (s): a quantile of the recent costs."""
        return self._expected

    def fits(self, left_s: float) -> bool:
        """Run the work now (``True``) with ``left_s`` seconds left before the next deadline, or
        put it off (``False``, counted). NaN counts as no time left."""
        if left_s >= self._expected:
            self._waited = 0
            return True
        if self._waited >= self.max_defer:
            self._waited = 0
            self.forced += 1
            return True
        self._waited += 1
        self.deferred += 1
        return False

    def record(self, cost_s: float) -> None:
        """What the work just took (s); non-finite or negative costs are ignored."""
        if not (math.isfinite(cost_s) and cost_s >= 0.0):
            return
        costs = self._costs
        costs.append(cost_s)
        ordered = sorted(costs)
        self._expected = ordered[min(len(ordered) - 1, int(self._quantile * len(ordered)))]
