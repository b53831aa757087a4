"""Per-stage wall-clock timing for the pipeline's ``stage_ms`` and for benchmarks.

Only ``time.perf_counter`` is read: no threads, no I/O.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np


class StageTimer:
    """Milliseconds spent per named stage; a stage timed twice accumulates.

    Example
    -------
    >>> timer = StageTimer()
    >>> with timer.stage("crop"):
    ...     pass
    >>> sorted(timer.ms)
    ['crop']
    """

    def __init__(self) -> None:
        self._ms: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the ``with`` block under ``name`` (also when it raises)."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._ms[name] = self._ms.get(name, 0.0) + (time.perf_counter() - t0) * 1e3

    @property
    def ms(self) -> Mapping[str, float]:
        """Read-only view ``stage -> milliseconds`` in first-timed order."""
        return MappingProxyType(self._ms)

    @property
    def total_ms(self) -> float:
        """Sum over the stages (ms)."""
        return float(sum(self._ms.values()))

    def reset(self) -> None:
        """Forget all stages (reuse the timer for the next frame)."""
        self._ms.clear()


@dataclass(frozen=True)
class TimingStats:
    """Summary of repeated measurements, in milliseconds."""

    n: int
    median_ms: float
    p90_ms: float
    min_ms: float
    max_ms: float

    def __str__(self) -> str:
        return f"median {self.median_ms:.3f} ms, p90 {self.p90_ms:.3f} ms (n={self.n})"


def timing_stats(samples_ms: Sequence[float]) -> TimingStats:
    """Median, 90th percentile, min and max of ``samples_ms`` (ms); zeros when empty."""
    arr = np.asarray(samples_ms, dtype=np.float64).reshape(-1)
    arr = arr[np.isfinite(arr)]
    if arr.size == 0:
        return TimingStats(0, 0.0, 0.0, 0.0, 0.0)
    return TimingStats(
        n=int(arr.size),
        median_ms=float(np.median(arr)),
        p90_ms=float(np.percentile(arr, 90)),
        min_ms=float(arr.min()),
        max_ms=float(arr.max()),
    )
