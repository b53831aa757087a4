"""Camera sources behind one small interface: ``read(timeout) -> DepthFrame | None``, ``close()``.

Choose one by kind with :func:`open_source` (``"simulated"``, ``"realsense"``; recordings come
later). Backends are imported only when chosen, so importing this package needs neither Open3D's
ray casting nor ``pyrealsense2``. :class:`SimulatedCameraSource` and :func:`simulated_pair` are
loaded on first access.
"""

from __future__ import annotations

from typing import Any

from .base import CameraSource, known_kinds, open_source, register_source

__all__ = [
    "CameraSource",
    "SimulatedCameraSource",
    "known_kinds",
    "open_source",
    "register_source",
    "simulated_pair",
]

_FROM_SIMULATED = {"SimulatedCameraSource", "SimulatedSourceConfig", "simulated_pair"}


def __getattr__(name: str) -> Any:
    if name in _FROM_SIMULATED:
        from . import simulated

        return getattr(simulated, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
