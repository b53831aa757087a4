"""The camera-source interface and the registry that finds backends lazily.

A source delivers :class:`~hapticloud.core.camera.DepthFrame` objects through one small
template (after python-can's ``BusABC``): subclasses implement :meth:`CameraSource._read` and
:meth:`CameraSource._close`; the base class keeps the counters the watchdogs read
(:attr:`~CameraSource.frames_received`, :attr:`~CameraSource.last_frame_time`), makes
:meth:`~CameraSource.close` idempotent and the source a context manager.

Backends are registered by kind. The shipped ones (``"simulated"``, ``"realsense"``) are imported
only when chosen, so a missing vendor driver (``pyrealsense2``) fails only when its kind is opened.

Example
-------
>>> from hapticloud.hardware.sources import open_source
>>> open_source("webcam")
Traceback (most recent call last):
...
hapticloud.core.errors.SourceError: source kind 'webcam': unknown (known: realsense, simulated)
"""

from __future__ import annotations

import importlib
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from types import TracebackType
from typing import Any, Self

from hapticloud.core.camera import DepthFrame
from hapticloud.core.errors import SourceError

__all__ = ["CameraSource", "known_kinds", "open_source", "register_source"]

Clock = Callable[[], float]


class CameraSource(ABC):
    """One depth camera (live, simulated or recorded), read by one consumer thread.

    Parameters
    ----------
    clock
        Monotonic clock in s, used for :attr:`last_frame_time` (``time.monotonic`` by default).
    """

    def __init__(self, *, clock: Clock = time.monotonic) -> None:
        self._clock = clock
        self._closed = False
        self._frames_received = 0
        self._last_frame_time: float | None = None

    # ----- template: what a backend implements -------------------------------------------------
    @property
    @abstractmethod
    def name(self) -> str:
        """Camera name (stamped on its frames)."""

    @abstractmethod
    def _read(self, timeout: float) -> DepthFrame | None:
        """The next frame, or None after at most ``timeout`` s (``timeout`` >= 0, finite)."""

    @abstractmethod
    def _close(self) -> None:
        """Release the device or stop the thread; called once."""

    # ----- public API --------------------------------------------------------------------------
    def read(self, timeout: float) -> DepthFrame | None:
        """The next frame, or None if none arrived within ``timeout`` s (never blocks longer).

        Raises :class:`SourceError` when the source is closed or has failed.
        """
        if not (isinstance(timeout, int | float) and math.isfinite(timeout) and timeout >= 0):
            raise SourceError(f"{self.name}: timeout = {timeout!r}: expected a finite s >= 0")
        if self._closed:
            raise SourceError(f"{self.name}: read from a closed source")
        frame = self._read(float(timeout))
        if frame is not None:
            self._frames_received += 1
            self._last_frame_time = self._clock()
        return frame

    def close(self) -> None:
        """Stop the source and release what it holds; calling it again does nothing."""
        if self._closed:
            return
        self._closed = True
        self._close()

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def frames_received(self) -> int:
        """Frames returned by :meth:`read` so far."""
        return self._frames_received

    @property
    def last_frame_time(self) -> float | None:
        """Clock time (monotonic s) at which :meth:`read` last returned a frame; None before."""
        return self._last_frame_time

    @property
    def frames_dropped(self) -> int:
        """Frames the source produced but nobody read before a newer one replaced them."""
        return 0

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<{type(self).__name__} {self.name!r} {state}>"


# ----- registry ------------------------------------------------------------------------------
SourceFactory = Callable[..., CameraSource]

#: Shipped backends as ``"module:function"``, imported on first use.
_LAZY: dict[str, str] = {
    "simulated": "hapticloud.hardware.sources.simulated:open_simulated",
    "realsense": "hapticloud.hardware.sources.realsense:open_realsense",
}
_FACTORIES: dict[str, SourceFactory] = {}


def register_source(kind: str, factory: SourceFactory) -> None:
    """Make ``open_source(kind, **kwargs)`` call ``factory(**kwargs)`` (replaces a lazy entry)."""
    if not isinstance(kind, str) or not kind:
        raise SourceError(f"source kind {kind!r}: expected a non-empty string")
    if not callable(factory):
        raise SourceError(f"source kind {kind!r}: factory is not callable")
    _FACTORIES[kind] = factory
    _LAZY.pop(kind, None)


def known_kinds() -> tuple[str, ...]:
    """Kinds :func:`open_source` accepts, sorted."""
    return tuple(sorted(set(_FACTORIES) | set(_LAZY)))


def _factory(kind: str) -> SourceFactory:
    factory = _FACTORIES.get(kind)
    if factory is not None:
        return factory
    target = _LAZY.get(kind)
    if target is None:
        raise SourceError(f"source kind {kind!r}: unknown (known: {', '.join(known_kinds())})")
    module_name, func_name = target.split(":")
    factory = getattr(importlib.import_module(module_name), func_name)
    _FACTORIES[kind] = factory
    return factory


def open_source(kind: str, **kwargs: Any) -> CameraSource:
    """Open a camera source of ``kind`` (``"simulated"``, ``"realsense"``, ...) with ``kwargs``.

    Raises :class:`SourceError` for an unknown kind (naming the known ones) or a backend that
    cannot be used here (e.g. ``pyrealsense2`` not installed).
    """
    return _factory(kind)(**kwargs)
