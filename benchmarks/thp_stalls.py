"""Stalls of real-time loops beside perception, with numpy's huge-page advice on or off.

Two probe processes (SCHED_FIFO 80, memory locked, collector off, like the control process) run an
800 Hz loop for ``--duration`` s: sleep to 200 µs before each deadline, spin to it, then spin
250 µs of "work". One of them also writes one row of a large array per tick (as the control
loop's log does). Each records every stall of more than 1 ms: a sleep that returned that late, or
a gap of that length between two clock reads while it spun. Meanwhile this process runs the loop
bench's perception load (both simulated D435s rendered and processed at 30 Hz).

``--advice on`` gives perception numpy's default (``madvise(MADV_HUGEPAGE)`` on arrays of 4 MiB or
more); ``off`` is what hapticloud sets (``core/threads.py``). The kernel's huge-page counters
(``/proc/vmstat``) are printed for the run.

    .venv/bin/python benchmarks/thp_stalls.py --advice on --duration 60
    .venv/bin/python benchmarks/thp_stalls.py --advice off --duration 60
"""

from __future__ import annotations

import argparse
import gc
import json
import multiprocessing as mp
import os
import sys
import time
from typing import Any

PERIOD_S = 1.0 / 800.0
SPIN_S = 200e-6
WORK_S = 250e-6
STALL_S = 1e-3


def probe(duration_s: float, write_rows: bool, conn: Any) -> None:
    """One 800 Hz loop; sends its stalls as ``[kind, t (s after start), length (ms)]``."""
    import numpy as np
    from hapticloud.core.threads import settle_numerics
    from hapticloud.hardware.control.deadline import lock_memory, try_sched_fifo

    settle_numerics(1)
    fifo, _ = try_sched_fifo(80)
    lock_memory()
    gc.collect()
    gc.freeze()
    gc.disable()
    rows = np.zeros((int(duration_s / PERIOD_S) + 2000, 20))
    clock = time.monotonic
    stalls: list[tuple[str, float, float]] = []
    t0 = clock() + 0.05
    end = t0 + duration_s
    k = i = 0
    last = clock()
    while True:
        k += 1
        t_k = t0 + k * PERIOD_S
        now = clock()
        if now > end:
            break
        if now - t_k > PERIOD_S:  # behind: resume on the next future deadline
            k = int((now - t0) / PERIOD_S) + 1
            t_k = t0 + k * PERIOD_S
        wake = t_k - SPIN_S
        if wake > now:
            time.sleep(wake - now)
            last = clock()
            if last - wake > STALL_S:
                stalls.append(("sleep", wake - t0, 1e3 * (last - wake)))
        if write_rows:
            rows[i, :] = now
            i += 1
        stop = t_k + WORK_S
        while True:
            t = clock()
            if t - last > STALL_S:
                stalls.append(("run", last - t0, 1e3 * (t - last)))
            last = t
            if t >= stop:
                break
    conn.send({"sched_fifo": fifo, "stalls": [(a, round(b, 3), round(c, 2)) for a, b, c in stalls]})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--advice", choices=("on", "off"), required=True)
    parser.add_argument("--duration", type=float, default=60.0)
    args = parser.parse_args(argv)
    from hapticloud.core.threads import numpy_hugepages, settle_numerics
    from hapticloud.hardware.control.bench import _Perception, machine_counters

    settle_numerics(1)
    perception = _Perception()  # turns the advice off, as a session's perception does
    numpy_hugepages(args.advice == "on")
    time.sleep(3.0)
    ctx = mp.get_context("spawn")
    probes = []
    for write_rows in (False, True):
        recv, send = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=probe, args=(args.duration, write_rows, send), daemon=True)
        proc.start()
        probes.append((write_rows, recv, proc))
    before = machine_counters()
    results = {}
    for write_rows, recv, proc in probes:
        name = "probe_writing_rows" if write_rows else "probe"
        results[name] = recv.recv() if recv.poll(args.duration + 60.0) else {"error": "no report"}
        proc.join(5.0)
    after = machine_counters()
    perc = perception.close()
    out = {
        "advice": args.advice,
        "duration_s": args.duration,
        **results,
        "counters": {k: after[k] - before[k] for k in before if k in after},
        "perception_frames": perc["frames_processed"],
    }
    sys.stdout.write(json.dumps(out) + "\n")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    raise SystemExit(main())
