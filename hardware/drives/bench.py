"""Cost of one bus cycle on a python-can bus pair: what the control loop pays for the bus.

One 800 Hz cycle is: encode and send the command frame and the SYNC (master), the six drives
answer (emulator), then receive and decode the six feedback frames into a snapshot (master).
The master's share is what the control tick pays; the emulator's share runs in the drives (or,
emulated, on another thread or process) and is reported apart.

The emulator runs stepped in the same thread with ``model_bus_timing=False`` so that answers are
available at once: the figures are CPU cost, not bus latency (the wire time of a cycle is
:func:`.schedule.config_load`'s ``busy_per_cycle_s``).
"""

from __future__ import annotations

import gc
import itertools
import time
from typing import Any

import can
import numpy as np

from . import codec
from . import protocol as p
from .config import DriveBusConfig
from .emulator import DriveEmulator, EmulatorConfig
from .link import DriveLink
from .protocol import DriveTarget
from .transport import SocketPairBus, socket_pair

_channels = itertools.count()


def _stats(samples_s: list[float]) -> dict[str, float]:
    us = np.asarray(samples_s) * 1e6
    return {
        "median_us": round(float(np.median(us)), 2),
        "p99_us": round(float(np.percentile(us, 99)), 2),
        "max_us": round(float(us.max()), 2),
    }


def bench_codec(repeats: int = 20000) -> dict[str, Any]:
    """Pure packing cost: one command encode plus six feedback decodes (no bus)."""
    cws = (p.CW_ENABLE_OPERATION,) * p.N_DRIVES
    tau = [1.0, -2.0, 3.0, -4.0, 5.0, -6.0]
    lim = [80.0] * p.N_DRIVES
    frames = [codec.encode_feedback(0.1 * i, 0.2, 0.3, 0x1237, 7, 7) for i in range(p.N_DRIVES)]
    samples = []
    for k in range(repeats):
        t0 = time.perf_counter()
        codec.encode_command(k, cws, tau, lim)
        for f in frames:
            codec.decode_feedback(f)
        samples.append(time.perf_counter() - t0)
    return _stats(samples)


def open_bus_pair(transport: str = "socketpair") -> tuple[can.BusABC, can.BusABC]:
    """A connected (master, drives) pair of CAN FD buses: ``"socketpair"`` (between processes,
    :mod:`.transport`) or ``"virtual"`` (python-can's in-process interface)."""
    if transport == "socketpair":
        a, b = socket_pair()
        return SocketPairBus(a, channel="master"), SocketPairBus(
            b, channel="drives", preserve_timestamps=True
        )
    if transport == "virtual":
        channel = f"drive-bus-{next(_channels)}"
        fd = can.CanProtocol.CAN_FD
        return (
            can.Bus(interface="virtual", channel=channel, protocol=fd),
            can.Bus(interface="virtual", channel=channel, protocol=fd, preserve_timestamps=True),
        )
    raise ValueError(f"transport = {transport!r}: expected 'socketpair' or 'virtual'")


def bench_cycle(
    cycles: int = 5000, warmup: int = 200, transport: str = "socketpair"
) -> dict[str, Any]:
    """Per-cycle cost of command + SYNC + six feedback frames through a bus pair.

    Returns the median, p99 and max (microseconds) of the master's share, the emulator's share
    and both, plus how many cycles came back incomplete (must be 0).
    """
    cfg = DriveBusConfig()
    master_bus, drive_bus = open_bus_pair(transport)
    try:
        link = DriveLink(master_bus, cfg)
        emu = DriveEmulator(
            drive_bus, cfg, EmulatorConfig(model_bus_timing=False, drive_response_s=0.0)
        )
        emu.step()
        link.start_nodes()
        emu.step()
        link.run_sequence(DriveTarget.ENABLED, timeout_s=2.0, pump=emu.step)
        link.poll_feedback()
        tau = np.array([0.5, -0.5, 0.5, -0.5, 0.2, -0.2])
        master, drives, incomplete = [], [], 0
        gc_was = gc.isenabled()
        gc.collect()
        gc.disable()  # the control process freezes the collector too; measure the same way
        try:
            for k in range(cycles + warmup):
                t0 = time.perf_counter()
                link.send_cycle(tau, link.controlwords(DriveTarget.ENABLED))
                t1 = time.perf_counter()
                emu.step()
                t2 = time.perf_counter()
                fb = link.poll_feedback()
                t3 = time.perf_counter()
                if k >= warmup:
                    master.append((t1 - t0) + (t3 - t2))
                    drives.append(t2 - t1)
                    incomplete += not fb.complete
        finally:
            if gc_was:
                gc.enable()
        total = [a + b for a, b in zip(master, drives, strict=True)]
        return {
            "cycles": cycles,
            "transport": transport,
            "master": _stats(master),
            "emulator": _stats(drives),
            "total": _stats(total),
            "incomplete_cycles": incomplete,
            "counters": link.counters._asdict(),
        }
    finally:
        master_bus.shutdown()
        drive_bus.shutdown()
