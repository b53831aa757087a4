"""``hapticloud bench safety``: the degradation table in worker processes, and the hardware row.

The cells are deterministic closed-loop runs (:mod:`hapticloud.core.studies.safety`), spread
over the machine's cores. The hardware row runs a scene in real time through the control process
and the emulated drives while a second process holds one core busy (the slow day, injected), and
judges it against the truth like every other run.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from hapticloud.core.studies.safety import (
    SCENES,
    Degradation,
    cell_from_report,
    degradations,
    run_cell,
)
from hapticloud.core.threads import settle_numerics


def _cell(job: tuple[str, Degradation, float | None]) -> dict[str, Any]:
    settle_numerics()
    return run_cell(*job)


def run_table(
    scenes: Sequence[str] = SCENES,
    rows: Sequence[Degradation] | None = None,
    duration_s: float | None = None,
    workers: int | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
) -> list[dict[str, Any]]:
    """Every (degradation, scene) cell in row order, on ``workers`` processes (default: cores)."""
    rows = degradations() if rows is None else list(rows)
    jobs = [(scene, row, duration_s) for row in rows for scene in scenes]
    n = workers or max(1, min(len(jobs), os.cpu_count() or 1))
    cells: list[dict[str, Any]] = []
    if n == 1:
        for job in jobs:
            cells.append(run_cell(*job))
            if progress is not None:
                progress(cells[-1])
        return cells
    with ProcessPoolExecutor(n, mp_context=mp.get_context("spawn")) as pool:
        for cell in pool.map(_cell, jobs):
            cells.append(cell)
            if progress is not None:
                progress(cell)
    return cells


def _hog(stop_at: float) -> None:
    """Hold one core busy until ``stop_at`` (monotonic s): the busy machine of a slow day."""
    x = 0
    while time.monotonic() < stop_at:
        for _ in range(10_000):
            x += 1


def hardware_cell(
    scene: str = "impacts",
    duration_s: float = 10.0,
    overrides: Mapping[str, Any] | None = None,
    busy_core: bool = True,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """``run SCENE --hardware`` with (by default) another process holding one core busy."""
    from .run import run_session

    hog = None
    if busy_core:
        # Start-up and the session's own wait for READY come first; the hog outlasts both.
        hog = mp.get_context("spawn").Process(
            target=_hog, args=(time.monotonic() + duration_s + 90.0,), daemon=True
        )
        hog.start()
    try:
        rep = run_session(scene, dict(overrides or {}), duration_s, progress=progress)
    finally:
        if hog is not None:
            hog.terminate()
            hog.join(5.0)
    name = "hardware path, one core busy" if busy_core else "hardware path"
    cell = cell_from_report(scene, name, overrides or {}, rep)
    cell["fused_valid_fraction"] = rep["estimates"].get("fused_valid_fraction")
    cell["estimates_sent"] = rep["estimates"].get("sent", {})
    return cell


__all__ = ["hardware_cell", "run_table"]
