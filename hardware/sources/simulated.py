"""Simulated D435 cameras as camera sources: rendered on absolute deadlines in a reader thread.

Each :class:`SimulatedCameraSource` owns one named daemon thread that renders frame ``k`` of its
camera at the deadline ``t_k = start + phase_s + k / rate_hz`` (clock time) with simulation time
``phase_s + k / rate_hz``, into a one-slot "latest frame" buffer: a newer frame replaces an unread
older one and the replaced one is counted in :attr:`~SimulatedCameraSource.frames_dropped`.
A deadline missed by more than one period (rendering too slow) is skipped, not caught up, and
counted in :attr:`~SimulatedCameraSource.deadlines_missed`.

``realtime=False`` starts no thread: :meth:`~SimulatedCameraSource.step` renders the next frame
synchronously, so tests are deterministic, and :meth:`~SimulatedCameraSource.capture` renders one
at a time a caller chooses, with the occluders and the region it chooses (what the perception
worker, :mod:`hapticloud.hardware.perception`, does on its own schedule).

Example
-------
>>> from hapticloud.core.sim import demo_scene
>>> scene = demo_scene(decimation=4)
>>> front, right = simulated_pair(scene, realtime=False)
>>> front.step().t, right.step().t, right.step().t
(0.0, 0.016666666666666666, 0.05)
>>> front.read(0.0).camera, right.frames_dropped
('front', 1)
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from hapticloud.core.camera import DepthFrame
from hapticloud.core.config import StageConfig, param
from hapticloud.core.errors import SourceError
from hapticloud.core.geometry.primitives import Primitive
from hapticloud.core.sim import SimDepthCamera, SimScene, SimWorld
from hapticloud.core.sim.raygrid import Window

from .base import CameraSource, Clock

__all__ = ["SimulatedCameraSource", "SimulatedSourceConfig", "open_simulated", "simulated_pair"]

OccludersAt = Callable[[float], Sequence[Primitive]]
#: A world that moves: ``world_at(t)`` -> the world at simulation time ``t`` s.
WorldAt = Callable[[float], SimWorld]


@dataclass(frozen=True)
class SimulatedSourceConfig(StageConfig):
    """Timing of one simulated camera."""

    _path: ClassVar[str] = "sources.simulated"

    rate_hz: float = param(30.0, lo=0.0, lo_open=True, hi=1000.0, unit="Hz", doc="frame rate")
    phase_s: float = param(0.0, lo=0.0, hi=10.0, unit="s", doc="time of the first frame")


class SimulatedCameraSource(CameraSource):
    """A :class:`~hapticloud.core.sim.SimDepthCamera` rendering ``world`` at ``rate_hz``.

    Parameters
    ----------
    camera, world
        What to render and what it sees: a :class:`~hapticloud.core.sim.SimWorld`, or a function
        of simulation time to one (bodies that move, e.g. a scene's ``MovingWorld.at``).
    occluders_at
        ``occluders_at(t)`` -> the robot's primitives at simulation time ``t`` s (none if None).
    rate_hz, phase_s
        Frame rate (Hz) and time of frame 0 after start (s); see :class:`SimulatedSourceConfig`.
    clock
        Monotonic clock in s (deadlines, :attr:`last_frame_time`).
    realtime
        True: a daemon thread renders on deadlines. False: call :meth:`step` to render.
    """

    def __init__(
        self,
        camera: SimDepthCamera,
        world: SimWorld | WorldAt,
        occluders_at: OccludersAt | None = None,
        rate_hz: float = 30.0,
        phase_s: float = 0.0,
        clock: Clock = time.monotonic,
        realtime: bool = True,
    ) -> None:
        super().__init__(clock=clock)
        if not isinstance(camera, SimDepthCamera):
            raise SourceError(f"camera: expected SimDepthCamera, got {type(camera).__name__}")
        if not (isinstance(world, SimWorld) or callable(world)):
            got = type(world).__name__
            raise SourceError(f"world: expected SimWorld or t -> SimWorld, got {got}")
        self.config = SimulatedSourceConfig(rate_hz=rate_hz, phase_s=phase_s)
        self._camera = camera
        self._world = world
        self._occluders_at = occluders_at
        self._realtime = bool(realtime)
        self._cond = threading.Condition()
        self._latest: DepthFrame | None = None
        self._error: BaseException | None = None
        self._k = 0
        self._produced = 0
        self._dropped = 0
        self._missed = 0
        self._stop = threading.Event()
        self._start = clock()
        self._thread: threading.Thread | None = None
        if self._realtime:
            self._thread = threading.Thread(
                target=self._run, name=f"hapticloud-camera-{camera.name}", daemon=True
            )
            self._thread.start()

    # ----- description -------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self._camera.name

    @property
    def camera(self) -> SimDepthCamera:
        return self._camera

    @property
    def thread(self) -> threading.Thread | None:
        """The render thread (None in stepping mode)."""
        return self._thread

    @property
    def frames_produced(self) -> int:
        """Frames rendered into the buffer so far."""
        return self._produced

    @property
    def frames_dropped(self) -> int:
        return self._dropped

    @property
    def deadlines_missed(self) -> int:
        """Frames skipped because rendering fell more than one period behind."""
        return self._missed

    def frame_time(self, k: int) -> float:
        """Simulation time (s) of frame ``k``: ``phase_s + k / rate_hz``."""
        return self.config.phase_s + k / self.config.rate_hz

    # ----- producing ---------------------------------------------------------------------------
    def _world_at(self, t: float) -> SimWorld:
        return self._world if isinstance(self._world, SimWorld) else self._world(t)

    def _render(self, k: int) -> DepthFrame:
        t = self.frame_time(k)
        occluders = tuple(self._occluders_at(t)) if self._occluders_at is not None else ()
        return self._camera.render(self._world_at(t), t, occluders)

    def _publish(self, frame: DepthFrame) -> None:
        with self._cond:
            if self._latest is not None:
                self._dropped += 1
            self._latest = frame
            self._produced += 1
            self._cond.notify_all()

    def step(self) -> DepthFrame:
        """Render the next frame now and put it in the buffer (stepping mode only)."""
        if self._realtime:
            raise SourceError(f"{self.name}: step() needs realtime=False")
        if self.closed:
            raise SourceError(f"{self.name}: step() on a closed source")
        frame = self._render(self._k)
        self._k += 1
        self._publish(frame)
        return frame

    def capture(
        self, t: float, occluders: Sequence[Primitive] = (), roi: Window | None = None
    ) -> DepthFrame:
        """Render the frame of simulation time ``t`` now, with ``occluders`` in front of the
        world and only the pixels of ``roi`` cast (all if None), and put it in the buffer
        (stepping mode only; the caller keeps the schedule)."""
        if self._realtime:
            raise SourceError(f"{self.name}: capture() needs realtime=False")
        if self.closed:
            raise SourceError(f"{self.name}: capture() on a closed source")
        frame = self._camera.render(self._world_at(t), t, occluders, roi=roi)
        self._publish(frame)
        return frame

    def _run(self) -> None:
        period = 1.0 / self.config.rate_hz
        try:
            while not self._stop.is_set():
                deadline = self._start + self.frame_time(self._k)
                late = self._clock() - deadline
                if late > period:  # fell behind: skip to the next future deadline
                    skip = int(late // period)
                    self._missed += skip
                    self._k += skip
                    continue
                if late < 0 and self._stop.wait(-late):
                    break
                frame = self._render(self._k)
                self._k += 1
                self._publish(frame)
        except Exception as exc:  # reported to the reader as a SourceError
            with self._cond:
                self._error = exc
                self._cond.notify_all()

    # ----- CameraSource ------------------------------------------------------------------------
    def _read(self, timeout: float) -> DepthFrame | None:
        with self._cond:
            if self._latest is None and self._error is None:
                self._cond.wait_for(
                    lambda: self._latest is not None or self._error is not None or self.closed,
                    timeout,
                )
            if self._latest is None and self._error is not None:
                raise SourceError(f"{self.name}: rendering failed: {self._error}")
            frame, self._latest = self._latest, None
            return frame

    def _close(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)


def simulated_pair(
    scene: SimScene,
    occluders_at: OccludersAt | None = None,
    *,
    rate_hz: float = 30.0,
    clock: Clock = time.monotonic,
    realtime: bool = True,
) -> tuple[SimulatedCameraSource, SimulatedCameraSource]:
    """The scene's two cameras, interleaved: ``cameras[0]`` at phase 0, ``cameras[1]`` half a
    period later (as the demo's two D435s are triggered)."""
    if len(scene.cameras) != 2:
        raise SourceError(f"scene {scene.name!r}: expected 2 cameras, got {len(scene.cameras)}")
    return tuple(  # type: ignore[return-value]
        SimulatedCameraSource(
            cam,
            scene.world,
            occluders_at,
            rate_hz=rate_hz,
            phase_s=i * 0.5 / rate_hz,
            clock=clock,
            realtime=realtime,
        )
        for i, cam in enumerate(scene.cameras)
    )


def open_simulated(
    *,
    camera: SimDepthCamera | str,
    world: SimWorld | None = None,
    scene: SimScene | None = None,
    **kwargs: Any,
) -> SimulatedCameraSource:
    """Registry factory: ``open_source("simulated", camera=cam, world=world, ...)`` or
    ``open_source("simulated", scene=scene, camera="front", ...)``."""
    if isinstance(camera, str):
        if scene is None:
            raise SourceError(f"simulated: camera = {camera!r} by name needs scene=")
        try:
            camera = scene.camera(camera)
        except Exception as exc:
            raise SourceError(f"simulated: {exc}") from None
    if world is None:
        if scene is None:
            raise SourceError("simulated: needs world= or scene=")
        world = scene.world
    return SimulatedCameraSource(camera, world, **kwargs)
