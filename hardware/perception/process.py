"""The perception worker in a process of its own (spawned), driven from its parent.

The child builds its worker with ``build(*args)`` (a module-level function: picklable at spawn;
pipes and shared-memory names in ``args`` travel too), answers ``("ready", camera names)``,
waits for ``("go", origin)`` (scene time 0 on :func:`time.monotonic`), runs until ``("stop",)``
and answers ``("result", stats)`` (:meth:`~.worker.PerceptionWorker.stats`); a failure is
answered as ``("error", traceback)``.
"""

from __future__ import annotations

import multiprocessing as mp
import traceback
from collections.abc import Callable
from typing import Any

from .worker import PerceptionWorker

__all__ = ["PerceptionProcess"]


def _child(build: Callable[..., PerceptionWorker], args: tuple[Any, ...], conn: Any) -> None:
    try:
        worker = build(*args)
        try:
            conn.send(("ready", worker.camera_names))
            msg = conn.recv()
            if msg[0] != "go":
                conn.send(("result", {}))
                return
            worker.start(float(msg[1]))
            worker.run(conn.poll)
        finally:
            worker.close()
        conn.send(("result", worker.stats()))
    except BaseException:
        try:
            conn.send(("error", traceback.format_exc()))
        except Exception:
            pass


class PerceptionProcess:
    """The parent's handle on a perception worker in a spawned process (see the module
    docstring): :meth:`wait_ready`, :meth:`go`, :meth:`stop`; :attr:`error` keeps a failure."""

    def __init__(
        self,
        build: Callable[..., PerceptionWorker],
        args: tuple[Any, ...],
        name: str = "hapticloud-perception",
    ) -> None:
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_child, args=(build, args, child), name=name, daemon=True)
        self._proc.start()
        child.close()
        self.error: str | None = None

    def _recv(self, timeout: float) -> tuple[str, Any]:
        if not self._conn.poll(timeout):
            raise TimeoutError("perception process did not answer in time")
        kind, payload = self._conn.recv()
        if kind == "error":
            self.error = payload
            raise RuntimeError(f"perception process failed:\n{payload}")
        return kind, payload

    def wait_ready(self, timeout: float = 60.0) -> list[str]:
        """The camera names, once the worker is built."""
        return self._recv(timeout)[1]

    def go(self, origin: float) -> None:
        """Start the cameras' schedule: scene time 0 is ``origin`` (:func:`time.monotonic`)."""
        self._conn.send(("go", origin))

    def stop(self, timeout: float = 10.0) -> dict[str, Any]:
        """Stop the worker; its stats (``{}`` if it failed or never went)."""
        out: dict[str, Any] = {}
        try:
            self._conn.send(("stop",))
            out = self._recv(timeout)[1]
        except (OSError, EOFError, RuntimeError, TimeoutError) as err:
            self.error = self.error or str(err) or type(err).__name__
        self._proc.join(timeout)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(2.0)
        self._conn.close()
        return out
