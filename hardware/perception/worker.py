"""The perception worker: cameras against the live robot, estimates to sinks.

One :class:`PerceptionWorker` owns, for every camera at once:

- **scheduling** (:class:`FrameSchedule`): camera ``k`` fires at ``origin + (phase_k + m /
  rate_k) / time_scale``; the earliest due camera goes first; frames the worker could not keep
  up with are dropped and counted (``skipped_frames``), as a camera's driver drops them;
- **the robot pose**: read from a :class:`RobotFeed` (the control process's shared state block,
  a fixed pose, a scripted path) at each capture; no pose yet, no capture;
- **occluders**: the robot's shapes at that pose (``occluders(pose)``), rendered in front of the
  world and left out by the crop;
- **time mapping**: the frame's scene time is ``(pose.t - origin) * time_scale`` (at least 0);
  its estimate is stamped with ``pose.t``, the :func:`time.monotonic` time the robot was there
  (the control loop's clock), or the time a free-running camera delivered it;
- **admission**: whether the loop's fusion takes the estimate
  (:func:`hapticloud.core.loop.admit` with the camera's ``min_quality``/``fuse_fallbacks``),
  counted and handed on with it; every estimate goes (an invalid one is fresh news too);
- **delivery**: each frame's :class:`~.sinks.Perceived` goes to every sink no earlier than the
  camera's ``latency_s`` after capture.

It runs in the caller's thread (:meth:`PerceptionWorker.run` with a stop-wait such as
``Event.wait`` or ``Connection.poll``), in a thread of its own
(:meth:`PerceptionWorker.start_thread`) or in a process (:class:`~.process.PerceptionProcess`).
Its clock is injectable, and :meth:`PerceptionWorker.step` does one round without sleeping, so
a test needs no real time.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np
from hapticloud.core.studies.stats import summary

from .channels import CameraChannel, ChannelSpec, RobotPose
from .sinks import Perceived, Sink

__all__ = ["FixedPose", "FrameSchedule", "PerceptionWorker", "RobotFeed", "no_occluders"]

Clock = Callable[[], float]
Occluders = Callable[[RobotPose], Sequence[Any]]

#: How often the worker looks at free-running cameras for a new frame (s).
STREAM_POLL_S = 0.005
#: The longest the worker sleeps with nothing due (s): it answers a stop at least this often.
IDLE_S = 0.01


class RobotFeed(Protocol):
    """Where the robot is now (``None``: not known yet)."""

    def read(self) -> RobotPose | None: ...


class FixedPose:
    """A robot that does not move: ``hip`` (and ``q``), at the time it is asked."""

    def __init__(self, hip: Any, q: Any = None, *, clock: Clock = time.monotonic) -> None:
        self._hip = np.asarray(hip, dtype=np.float64)
        self._q = None if q is None else np.asarray(q, dtype=np.float64)
        self._clock = clock

    def read(self) -> RobotPose:
        return RobotPose(self._clock(), self._hip, self._q)


def no_occluders(_pose: RobotPose) -> tuple[Any, ...]:
    """Nothing in front of the world (a probe without a robot)."""
    return ()


class FrameSchedule:
    """When each scheduled camera's next frame is due (clock time), and the frames skipped.

    Pure bookkeeping over clock times: no sleeping, no reading of a clock.
    """

    def __init__(
        self,
        specs: Sequence[ChannelSpec],
        origin: float,
        time_scale: float = 1.0,
        catch_up: bool = False,
    ) -> None:
        self._scale = float(time_scale)
        self._catch_up = bool(catch_up)
        self.next_t = [origin + spec.phase_s / self._scale for spec in specs]
        self._step = [1.0 / (spec.rate_hz * self._scale) for spec in specs]
        self.skipped = [0] * len(specs)

    def due(self, now: float) -> int | None:
        """The index of the earliest frame due by ``now``, or ``None``."""
        best = None
        for i, t in enumerate(self.next_t):
            if t <= now and (best is None or t < self.next_t[best]):
                best = i
        return best

    def advance(self, i: int, now: float) -> None:
        """Camera ``i`` took its frame; its next one is the first on its grid after ``now``
        (those in between are skipped and counted), or with ``catch_up`` the newest of those
        in between, due at once (the others skipped)."""
        step = self._step[i]
        nxt = self.next_t[i] + step
        if nxt <= now:
            missed = math.floor((now - nxt) / step) + 1
            if self._catch_up:
                missed -= 1
            self.skipped[i] += missed
            nxt += missed * step
        self.next_t[i] = nxt

    def next_due(self) -> float:
        return min(self.next_t, default=math.inf)


class PerceptionWorker:
    """Cameras against a robot, estimates to sinks (see the module docstring).

    Parameters
    ----------
    channels
        The cameras (:class:`~.channels.CameraChannel`), names unique.
    robot
        The robot's pose (:class:`RobotFeed`).
    sinks
        Where each :class:`~.sinks.Perceived` goes (:mod:`.sinks`).
    occluders
        The robot's shapes at a pose (default: none).
    clock
        Monotonic clock (s): the control loop's (``time.monotonic``) unless a test injects one.
    time_scale
        Scene seconds per clock second (a slowed-down display: < 1).
    catch_up
        A camera whose frame took longer than its period takes its next frame at once (the
        newest it missed) instead of waiting for the next on its grid: a simulated camera whose
        rendering, not its exposure, was late (the live app on a loaded machine). Off: frames
        on the grid are dropped, as a camera's driver drops them.
    """

    def __init__(
        self,
        channels: Sequence[CameraChannel],
        robot: RobotFeed,
        sinks: Sequence[Sink] = (),
        *,
        occluders: Occluders = no_occluders,
        clock: Clock = time.monotonic,
        time_scale: float = 1.0,
        catch_up: bool = False,
    ) -> None:
        names = [c.name for c in channels]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique: {names}")
        if not (math.isfinite(time_scale) and time_scale > 0.0):
            raise ValueError(f"time_scale = {time_scale}: expected a positive number")
        self.channels = list(channels)
        self.robot = robot
        self.sinks = list(sinks)
        self._occluders = occluders
        self._clock = clock
        self.time_scale = float(time_scale)
        self.catch_up = bool(catch_up)
        self._scheduled = [c for c in self.channels if not c.free_running]
        self._streams = [c for c in self.channels if c.free_running]
        self.origin: float | None = None
        self._schedule: FrameSchedule | None = None
        self._pending: list[tuple[float, Perceived]] = []
        self._frames = dict.fromkeys(names, 0)
        self._valid = dict.fromkeys(names, 0)
        self._admitted = dict.fromkeys(names, 0)
        self._perception_ms: list[float] = []
        self._delivery_ms: list[float] = []
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.errors: list[str] = []

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.channels]

    # ----- time ----------------------------------------------------------------------------------
    def start(self, origin: float | None = None) -> None:
        """Scene time 0 is clock time ``origin`` (default: now); the schedule starts there."""
        self.origin = self._clock() if origin is None else float(origin)
        specs = [c.spec for c in self._scheduled]
        self._schedule = FrameSchedule(specs, self.origin, self.time_scale, self.catch_up)

    def scene_time(self, t: float) -> float:
        """The scene time of clock time ``t`` (never before 0)."""
        assert self.origin is not None, "start() first"
        return max(0.0, (t - self.origin) * self.time_scale)

    # ----- one round -----------------------------------------------------------------------------
    def step(self) -> float:
        """Deliver what is due, capture the earliest due frame (if any); returns the clock time
        at which the worker next has something to do (now: call again at once)."""
        if self._schedule is None:
            raise RuntimeError("PerceptionWorker.step() before start()")
        now = self._clock()
        self._deliver(now)
        for channel in self._streams:
            self._capture(channel)
        i = self._schedule.due(now)
        if i is not None:
            self._capture(self._scheduled[i])
            self._schedule.advance(i, self._clock())
            return self._clock()
        wake = min(now + IDLE_S, self._schedule.next_due())
        if self._pending:
            wake = min(wake, self._pending[0][0])
        if self._streams:
            wake = min(wake, now + STREAM_POLL_S)
        return wake

    def _capture(self, channel: CameraChannel) -> None:
        pose = self.robot.read()
        if pose is None:
            return
        occluders = self._occluders(pose) if channel.sees_occluders else ()
        full_frame = any(s.wants_frames for s in self.sinks)
        p0 = time.perf_counter()
        cap = channel.capture(self.scene_time(pose.t), pose, occluders, full_frame)
        if cap is None:
            return
        took_ms = (time.perf_counter() - p0) * 1e3
        self._perception_ms.append(took_ms)
        self._perceived(channel, pose, occluders, cap, took_ms)

    def _perceived(
        self, channel: CameraChannel, pose: RobotPose, occluders: Any, cap: Any, took_ms: float
    ) -> None:
        from hapticloud.core.loop import admit

        spec = channel.spec
        captured = pose.t if cap.captured is None else float(cap.captured)
        seq = self._frames[spec.name]
        est = dataclasses.replace(cap.estimate, t=captured, seq=seq)
        admitted = admit(est, spec.min_quality, spec.fuse_fallbacks)
        self._frames[spec.name] += 1
        self._valid[spec.name] += bool(est.valid)
        self._admitted[spec.name] += admitted
        item = Perceived(
            spec.name,
            seq,
            self.scene_time(captured),
            captured,
            est,
            cap.frame,
            pose.hip,
            pose.q,
            occluders,
            admitted,
            took_ms,
        )
        due = captured + spec.latency_s
        self._pending.append((due, item))
        self._pending.sort(key=lambda entry: entry[0])
        self._deliver(self._clock())

    def _deliver(self, now: float) -> None:
        while self._pending and self._pending[0][0] <= now:
            item = self._pending.pop(0)[1]
            for sink in self.sinks:
                sink.put(item)
            self._delivery_ms.append((self._clock() - item.captured) * 1e3)

    # ----- running -------------------------------------------------------------------------------
    def run(self, wait_stop: Callable[[float], bool]) -> None:
        """Run rounds until ``wait_stop(timeout)`` (waits up to ``timeout`` s, True: stop; e.g.
        ``threading.Event.wait`` or a pipe's ``poll``) says so. Starts now if not started."""
        if self._schedule is None:
            self.start()
        while True:
            wake = self.step()
            if wait_stop(max(0.0, wake - self._clock())):
                return

    def start_thread(
        self,
        origin: float | None = None,
        name: str = "hapticloud-perception",
        nice: int | None = None,
    ) -> None:
        """Run in a daemon thread of its own from ``origin``; :meth:`stop_thread` ends it. A
        failure ends the thread and is kept in :attr:`errors`. ``nice``: the thread's (and the
        threads it starts') niceness (Linux; 19: what is left after everything else), so that
        perception yields the CPUs to the processes around the control loop."""
        if self._thread is not None:
            raise RuntimeError("the perception thread is already running")
        self.start(origin)
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._thread_main, args=(nice,), name=name, daemon=True
        )
        self._thread.start()

    def _thread_main(self, nice: int | None) -> None:
        if nice is not None:
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
            except (OSError, AttributeError):
                pass  # not Linux, or not allowed: perception at the usual priority
        try:
            self.run(self._stop.wait)
        except Exception:
            self.errors.append(traceback.format_exc())

    def stop_thread(self, timeout: float = 2.0) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout)
            self._thread = None

    def close(self) -> None:
        """Stop the thread (if any) and close the channels' sources and the robot feed."""
        self.stop_thread()
        for channel in self.channels:
            channel.close()
        close = getattr(self.robot, "close", None)
        if close is not None:
            close()

    # ----- figures -------------------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """Per camera: frames ``sent`` (captured and handed on), ``valid``, ``admitted``,
        ``skipped_frames``; ``perception_ms`` (render + process) and ``capture_to_send_ms``
        (capture to the sinks) as median, p99 and max; ``sink_dropped``: what each sink that
        counts them dropped, by the sink's class name. Frames still held for their latency at
        the stop are counted as sent but reach no sink."""
        skipped = self._schedule.skipped if self._schedule is not None else []
        return {
            "sent": dict(self._frames),
            "valid": dict(self._valid),
            "admitted": dict(self._admitted),
            "skipped_frames": {
                **dict.fromkeys(self._frames, 0),
                **{c.name: n for c, n in zip(self._scheduled, skipped, strict=False)},
            },
            "perception_ms": _spread(self._perception_ms),
            "capture_to_send_ms": _spread(self._delivery_ms),
            "sink_dropped": {
                type(s).__name__: int(s.dropped) for s in self.sinks if hasattr(s, "dropped")
            },
        }


def _spread(values: list[float]) -> dict[str, float | int | None]:
    """Median, p99 and max of the finite values (JSON-safe)."""
    return summary(np.array(values), 1.0, percentiles=(99,), count=False)
