"""Stalls a real-time loop gets from the machine alone: no load, one probe loop per CPU.

Each probe (SCHED_FIFO 80, memory locked, collector off, pinned to its CPU) runs an 800 Hz loop
for ``--duration`` s as the control loop does: sleep to 200 µs before each deadline, spin to it,
then spin 250 µs of "work". It records every stall of more than 1 ms (a sleep that returned that
late, or a gap of that length between two clock reads while it spun) and whether the kernel
switched the probe out involuntarily during it (``ru_nivcsw``): with no such switch, no task of
this machine took the CPU, and the time went to the kernel's own work or to the hypervisor.
Meanwhile this process samples the per-CPU steal time of ``/proc/stat`` every 2 ms.

``--qos`` holds ``/dev/cpu_dma_latency`` at 0 µs for the run (idle CPUs poll instead of
halting, what ``cyclictest`` does); needs root.

    .venv/bin/python benchmarks/vm_stalls.py --duration 60
    .venv/bin/python benchmarks/vm_stalls.py --duration 60 --qos
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import struct
import sys
import time
from typing import Any

PERIOD_S = 1.0 / 800.0
SPIN_S = 200e-6
WORK_S = 250e-6
STALL_S = 1e-3


def probe(cpu: int, duration_s: float, conn: Any) -> None:
    """One 800 Hz loop on ``cpu``; sends ``[kind, t (monotonic), ms, switched_out]`` stalls."""
    from hapticloud.hardware.control.deadline import DeadlineLoop, lock_memory

    os.sched_setaffinity(0, {cpu})
    lock_memory()
    # The control loop's own pacing: sleep to SPIN_S before each deadline, spin to it.
    loop = DeadlineLoop(PERIOD_S, spin_s=SPIN_S, fifo_priority=80)
    clock = time.perf_counter  # CLOCK_MONOTONIC, as time.monotonic

    def switches() -> int:
        return resource.getrusage(resource.RUSAGE_THREAD).ru_nivcsw

    stalls: list[tuple[str, float, float, bool]] = []
    loop.start()
    end = clock() + duration_s
    try:
        while True:
            seen = switches()
            _, t_k = loop.wait()
            last = clock()
            if last > end:
                break
            if last - t_k > STALL_S:
                n = switches()
                stalls.append(("wake", t_k, 1e3 * (last - t_k), n != seen))
                seen = n
            stop = t_k + WORK_S
            while True:
                t = clock()
                if t - last > STALL_S:
                    n = switches()
                    stalls.append(("run", last, 1e3 * (t - last), n != seen))
                    seen = n
                last = t
                if t >= stop:
                    break
            loop.done()
    finally:
        loop.stop()
    st = loop.stats()
    conn.send(
        {
            "cpu": cpu,
            "sched_fifo": st.sched_fifo,
            "ticks": st.ticks,
            "misses": st.misses + st.skipped,
            "stalls": stalls,
        }
    )


def _steal() -> dict[int, int]:
    out = {}
    with open("/proc/stat") as f:
        for line in f:
            if line.startswith("cpu") and line[3].isdigit():
                fields = line.split()
                out[int(fields[0][3:])] = int(fields[8])
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--qos", action="store_true", help="hold /dev/cpu_dma_latency at 0")
    args = parser.parse_args(argv)
    qos = None
    if args.qos:
        try:
            qos = os.open("/dev/cpu_dma_latency", os.O_WRONLY)
            os.write(qos, struct.pack("i", 0))
        except OSError as err:
            sys.stderr.write(f"vm_stalls: /dev/cpu_dma_latency: {err}\n")
            return 2
    cpus = sorted(os.sched_getaffinity(0))
    ctx = mp.get_context("spawn")
    probes = []
    for cpu in cpus:
        recv, send = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=probe, args=(cpu, args.duration, send), daemon=True)
        proc.start()
        probes.append((recv, proc))
    tick_s = 1.0 / os.sysconf("SC_CLK_TCK")
    steal_t: dict[int, list[float]] = {c: [] for c in cpus}
    last = _steal()
    end = time.monotonic() + args.duration + 2.0
    while time.monotonic() < end:
        now = _steal()
        for c in cpus:
            if now.get(c, 0) != last.get(c, 0):
                steal_t[c].append(time.monotonic())
        last = now
        time.sleep(0.002)
    out: dict[str, Any] = {"duration_s": args.duration, "qos": args.qos, "cpus": []}
    for recv, proc in probes:
        res = recv.recv() if recv.poll(60.0) else {"error": "no report"}
        proc.join(5.0)
        if "stalls" in res:
            near = steal_t.get(res["cpu"], [])
            res["steal_increments"] = len(near)
            res["stalls"] = [
                {
                    "kind": kind,
                    "ms": round(ms, 2),
                    "switched_out": switched,
                    "steal_within_25ms": any(abs(t - s) < 0.025 for s in near),
                }
                for kind, t, ms, switched in res["stalls"]
            ]
            res["stalls_per_10k_ticks"] = round(1e4 * len(res["stalls"]) / max(res["ticks"], 1), 2)
            res["stalls_without_switch"] = sum(not s["switched_out"] for s in res["stalls"])
        out["cpus"].append(res)
    out["steal_tick_s"] = tick_s
    if qos is not None:
        os.close(qos)
    sys.stdout.write(json.dumps(out) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
