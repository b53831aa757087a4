"""The six emulated drives in their own process, on the far end of a :mod:`.transport` bus.

Real drives compute their answers on their own hardware while the master computes the next
command. Run in the control process (stepped, or on a thread), the emulator's ~150 µs per cycle
of arm dynamics and frame handling would be charged to the control tick, and its thread would
compete for the control process's GIL. Here it runs in a ``spawn`` child of its own, talking CAN
FD over a :class:`~.transport.SocketPairBus`: the tick then pays only what it pays on a real bus
(its own frames' system calls).

The child is told what to emulate by the first message on its command pipe (``init``: bus and
emulator configs, URDF, initial joint positions, arm dynamics options), then takes fault
injections (``inject``: a :class:`~.faults.FaultInjector` method and its arguments) and ``stop``,
to which it answers with its event history. It runs the emulator's own thread
(:meth:`DriveEmulator.start`, bus timing model included) at ``SCHED_FIFO`` when permitted, one
priority below the control loop, and stops when the pipe closes (its parent is gone).

:func:`spawn_emulator` starts it from the process that will join it (the control process is a
daemon and may not have children, so its parent does); the control process commands it through
an :class:`EmulatorHandle` on the pipe end it was given.
"""

from __future__ import annotations

import gc
import multiprocessing as mp
import socket
import traceback
from typing import Any

__all__ = ["EmulatorHandle", "join_process", "spawn_emulator"]


def _emulator_main(sock: socket.socket, conn: Any) -> None:
    try:
        _run(sock, conn)
    except BaseException:
        try:
            conn.send(("error", traceback.format_exc()))
        except Exception:
            pass


def _run(sock: socket.socket, conn: Any) -> None:
    from hapticloud.core.robot.model import RobotModel
    from hapticloud.core.threads import settle_numerics

    from ..control.deadline import lock_memory, try_sched_fifo
    from .emulator import DriveEmulator, RigidArm
    from .faults import FAULT_METHODS
    from .transport import SocketPairBus

    settle_numerics(1)
    kind, init = conn.recv()
    if kind != "init":
        raise RuntimeError(f"emulator process: expected 'init' first, got {kind!r}")
    bus = SocketPairBus(sock, preserve_timestamps=True, channel="drives")
    model = RobotModel.load(init["urdf"])
    dynamics = init.get("dynamics")
    arm = dynamics(model) if dynamics is not None else None
    if arm is None:
        arm = RigidArm(model, init["emulator"].joint_damping_nms)
    emu = DriveEmulator(
        bus, init["bus"], init["emulator"], dynamics=arm, model=model, q0=init["q0"]
    )
    fifo = init.get("fifo_priority")
    sched = try_sched_fifo(fifo) if fifo is not None else (False, "not requested")
    # Like the control process: no page faults, no collector pauses. A pause here holds the
    # drives' answers back, and past feedback_lost_s the master turns the torque off.
    _, lock_note = lock_memory()
    gc.collect()
    gc.freeze()
    gc.disable()
    emu.start()
    conn.send(("ready", {"sched_fifo": sched[0], "sched_note": sched[1], "mlockall": lock_note}))
    try:
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                return
            if msg[0] == "stop":
                break
            if msg[0] == "inject":
                _, method, args, kwargs = msg
                if method in FAULT_METHODS:
                    getattr(emu.faults, method)(*args, **kwargs)
    finally:
        emu.stop()
        bus.shutdown()
    conn.send(("result", {"events": [tuple(e) for e in emu.events()][-256:]}))


class EmulatorHandle:
    """Commands to the emulator child over its pipe (they never block the loop: a few dozen
    bytes on a pipe with room for thousands).

    The control process holds this over the pipe end :func:`spawn_emulator` returned; only the
    process that spawned the child (``proc``) can join it.
    """

    def __init__(self, conn: Any, proc: Any = None) -> None:
        self._proc = proc
        self._conn = conn
        self.info: dict[str, Any] | None = None
        self.error: str | None = None

    def init(self, init: dict[str, Any]) -> None:
        """What to emulate: ``bus`` (:class:`~.config.DriveBusConfig`), ``emulator``
        (:class:`~.emulator.EmulatorConfig`), ``urdf`` (path or ``None``), ``q0`` (rad),
        ``fifo_priority`` (``None``: normal scheduler), ``dynamics`` (``None`` or a picklable
        callable ``model -> ArmDynamics``)."""
        self._conn.send(("init", init))

    def wait_ready(self, timeout: float = 30.0) -> dict[str, Any]:
        if not self._conn.poll(timeout):
            raise TimeoutError("drive emulator process did not start in time")
        kind, payload = self._conn.recv()
        if kind != "ready":
            raise RuntimeError(f"drive emulator process failed at start-up:\n{payload}")
        self.info = payload
        return payload

    def inject(self, method: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
        self._conn.send(("inject", method, args, kwargs))

    def stop(self, timeout: float = 3.0) -> list[tuple[Any, ...]]:
        """Stop the child; returns its last events (empty if it could not say)."""
        events: list[tuple[Any, ...]] = []
        try:
            self._conn.send(("stop",))
            if self._conn.poll(timeout):
                kind, payload = self._conn.recv()
                if kind == "result":
                    events = payload["events"]
                else:
                    self.error = payload
        except (EOFError, OSError, BrokenPipeError):
            pass
        if self._proc is not None:
            join_process(self._proc, timeout)
        self._conn.close()
        return events


def join_process(proc: Any, timeout: float = 3.0) -> None:
    """Join a child, terminating it if it does not end in ``timeout`` seconds."""
    proc.join(timeout)
    if proc.is_alive():
        proc.terminate()
        proc.join(1.0)


def spawn_emulator(sock: socket.socket) -> tuple[Any, Any]:
    """Start the emulator child on ``sock`` (one end of :func:`.transport.socket_pair`).

    Returns ``(process, pipe end)``: wrap the pipe end in :class:`EmulatorHandle` where the
    commands come from (it may be sent to another process), send :meth:`EmulatorHandle.init`
    first; join ``process`` from here.
    """
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe(duplex=True)
    proc = ctx.Process(
        target=_emulator_main, args=(sock, child), name="hapticloud-drives", daemon=True
    )
    proc.start()
    child.close()
    return proc, parent
