"""Trials on a Dask cluster: cached ones are read, the others submitted, results streamed back
in the order they finish; Ctrl-C cancels what has not finished and keeps what has."""

from __future__ import annotations

import dataclasses
import socket
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from hapticloud.core.studies.trade.evaluate import OBJECTIVES, TrialResult, TrialSpec, evaluate

from .cache import TrialCache

_SETTLED = False


def run_trial(spec: TrialSpec, budget_mm: float | None = None) -> TrialResult:
    """One trial, on the worker it was sent to (recorded in the result: latency is that
    machine's)."""
    global _SETTLED
    if not _SETTLED:
        from hapticloud.core.threads import settle_numerics

        settle_numerics(1)
        _SETTLED = True
    try:
        if spec.recordings:
            from .recording import recorded_frames

            result = evaluate(spec, budget_mm=budget_mm, recorded_frames=recorded_frames)
        else:
            result = evaluate(spec, budget_mm=budget_mm)
    except Exception as err:  # a trial's crash is its finding, not the study's end
        text = f"exception {type(err).__name__}: {err}".splitlines()[0]
        nan = dict.fromkeys(OBJECTIVES, float("nan"))
        result = TrialResult(spec.params, nan, True, (text,), problems=(text,))
    return dataclasses.replace(result, worker=_where())


def _where() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return f"local@{socket.gethostname()}"


@dataclass
class Outcome:
    """The trials in the order given (``None``: not finished) and whether Ctrl-C stopped it."""

    results: list[TrialResult | None]
    interrupted: bool = False
    measured: int = 0
    cached: int = 0
    stopped: list[int] = field(default_factory=list)

    @property
    def finished(self) -> list[TrialResult]:
        return [r for r in self.results if r is not None]


Callback = Callable[[int, TrialResult], None]


def run_trials(
    client: Any,
    specs: Sequence[TrialSpec],
    cache: TrialCache,
    on_done: Callback | None = None,
    *,
    budget_mm: float | None = None,
) -> Outcome:
    """Run ``specs`` (cached ones read back); ``on_done(index, result)`` as each finishes."""
    from distributed import as_completed

    outcome = Outcome([None] * len(specs))
    pending: dict[Any, int] = {}
    for i, spec in enumerate(specs):
        hit = cache.get(spec)
        if hit is not None:
            outcome.results[i] = dataclasses.replace(hit, params=dict(spec.params))
            outcome.cached += 1
            if on_done is not None:
                on_done(i, outcome.results[i])
    try:
        for i, spec in enumerate(specs):
            if outcome.results[i] is None:
                # pure=False: a trial is measured again when asked (latency is not a pure value).
                pending[client.submit(run_trial, spec, budget_mm, pure=False)] = i
        for future in as_completed(list(pending)):
            i = pending.pop(future)
            result = dataclasses.replace(future.result(), params=dict(specs[i].params))
            cache.put(specs[i], result)
            outcome.results[i] = result
            outcome.measured += 1
            if on_done is not None:
                on_done(i, result)
    except KeyboardInterrupt:
        outcome.interrupted = True
        outcome.stopped = sorted(pending.values())
        client.cancel(list(pending))
    return outcome


__all__ = ["Outcome", "run_trial", "run_trials"]
