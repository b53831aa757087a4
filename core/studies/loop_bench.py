"""``hapticloud bench loop``: the 800 Hz control tick timed in a closed loop.

The tick (:meth:`~hapticloud.core.loop.HapticLoop.tick`: fusion sample, robot dynamics, haptic
constraint rows, hierarchical controller, torque clamp) runs inside the closed-loop simulation of
a scene, so it sees the states, surfaces and constraint activity of a real session: the
exoskeleton simulated with the patient's arm, and the fusion fed at 60 Hz. The cameras are
switched to the ``oracle`` model (the true closest point with noise) so that rendering does not
dominate the run; perception runs outside the tick anyway (camera threads on the robot).

Only the tick is timed (``perf_counter`` inside it); between ticks the simulator integrates the
plant, as the drive bus I/O would on the robot, which leaves the caches as cold as they will be
there. A *miss* is a tick longer than the 1250 µs period (the tick alone, without bus I/O: the
budget it must leave for it). Garbage collection stays on; the objects built before the loop are
frozen out of it (``gc.freeze``), as the control thread of the hardware layer does.
"""

from __future__ import annotations

import gc
import json
import platform
import time
from collections.abc import Mapping
from typing import Any, TextIO

import numpy as np

from ..scene import load_scene
from ..scene.assembly import assemble
from ..sim.closed_loop import ClosedLoopSim
from .run import DEADLINE_US, constraint_stats, control_stats, run_verdict
from .verdict import UNSAFE_EXIT_CODE

TARGETS = {"tick_us_median": 150.0, "tick_us_p99": 400.0}


def run_bench(
    scene: str = "impacts",
    duration_s: float = 15.0,
    overrides: Mapping[str, Any] | None = None,
    *,
    oracle: bool = True,
) -> dict[str, Any]:
    """Run ``scene`` for ``duration_s`` simulated seconds and time every tick.

    Returns the JSON-ready result (``tick_us_median``, ``tick_us_p99``, ``misses_per_10k``, ...).
    """
    loaded = load_scene(scene, overrides)
    if oracle and loaded.cameras:
        loaded = loaded.with_overrides(
            {f"cameras.{c.name}.model": "oracle" for c in loaded.cameras}
        )
    sim = ClosedLoopSim(assemble(loaded))
    gc.collect()
    gc.freeze()
    t0 = time.perf_counter()
    try:
        record = sim.run(duration_s)
    finally:
        gc.unfreeze()
    wall = time.perf_counter() - t0
    a = record.arrays
    tick = a["tick_us"]
    rows = a["rows"] > 0
    solving = a["solve_us"] > 0.0
    ctl = control_stats(record)
    result = {
        "scene": loaded.name,
        "cameras": "oracle" if oracle else "rendered",
        "ticks": int(tick.size),
        "tick_us_median": float(np.median(tick)),
        "tick_us_p99": float(np.percentile(tick, 99)),
        "tick_us_max": float(tick.max()),
        "misses_per_10k": float(1e4 * np.count_nonzero(tick > DEADLINE_US) / tick.size),
        "deadline_us": DEADLINE_US,
        "miss_definition": "tick (without bus I/O) longer than the 1250 us period",
        "tick_us_median_with_constraint_rows": float(np.median(tick[rows])) if rows.any() else None,
        "tick_us_median_without_rows": float(np.median(tick[~rows])) if (~rows).any() else None,
        "rows_fraction": float(rows.mean()),
        # Over all ticks (most skip the solver), then over the ticks that solved the hierarchy.
        "controller_step_us_median": float(np.median(a["step_us"])),
        "solve_us_median": float(np.median(a["solve_us"])),
        "solving_fraction": float(solving.mean()),
        "controller_step_us_median_solving": (
            float(np.median(a["step_us"][solving])) if solving.any() else None
        ),
        "solve_us_median_solving": float(np.median(a["solve_us"][solving]))
        if solving.any()
        else None,
        "outside_controller_us_median": float(np.median(tick - a["step_us"])),
        "statuses": ctl["statuses"],
        "constraints": constraint_stats(record),
        "targets": TARGETS,
        "wall_time_s": wall,
        # The run is a closed loop against the simulator's truth: it says whether it was safe.
        "truth": run_verdict(record).to_json(),
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    result["pass"] = bool(
        result["tick_us_median"] <= TARGETS["tick_us_median"]
        and result["tick_us_p99"] <= TARGETS["tick_us_p99"]
    )
    return result


def main(
    scene: str,
    duration_s: float,
    overrides: Mapping[str, Any] | None,
    as_json: bool,
    out: TextIO,
    *,
    oracle: bool = True,
) -> int:
    """CLI entry: print the result (one JSON object with ``as_json``)."""
    res = run_bench(scene, duration_s, overrides, oracle=oracle)
    if as_json:
        out.write(json.dumps(res) + "\n")
        return 0
    out.write(
        f"loop tick ({res['scene']}, {res['ticks']} ticks, cameras {res['cameras']}): "
        f"median {res['tick_us_median']:.0f} us, p99 {res['tick_us_p99']:.0f} us, "
        f"max {res['tick_us_max']:.0f} us, misses {res['misses_per_10k']:.1f} per 10,000 "
        f"(> {DEADLINE_US:.0f} us)\n"
        f"  with constraint rows: median {res['tick_us_median_with_constraint_rows'] or 0:.0f} us "
        f"({100 * res['rows_fraction']:.0f} % of ticks); controller step "
        f"{res['controller_step_us_median']:.0f} us, the rest "
        f"{res['outside_controller_us_median']:.0f} us; on the "
        f"{100 * res['solving_fraction']:.0f} % of ticks that solve the hierarchy, step "
        f"{res['controller_step_us_median_solving'] or 0:.0f} us (solve "
        f"{res['solve_us_median_solving'] or 0:.0f} us)\n"
        f"  targets: median <= {TARGETS['tick_us_median']:.0f} us, p99 <= "
        f"{TARGETS['tick_us_p99']:.0f} us: {'pass' if res['pass'] else 'FAIL'}\n"
        f"{res['truth']['line']}\n"
    )
    return UNSAFE_EXIT_CODE if res["truth"]["safe"] is False else 0


__all__ = ["TARGETS", "main", "run_bench"]
