"""The perception worker: its schedule, time mapping, admission, occluders and sinks, on an
injected clock (no real time except where a thread is the point)."""

from __future__ import annotations

import math
import multiprocessing as mp
import queue
import threading
import time

import numpy as np
import pytest
from hapticloud.core.perception import CameraPipeline, SurfaceEstimate
from hapticloud.core.sim import demo_scene
from hapticloud.hardware.control.messages import estimate_from_wire
from hapticloud.hardware.perception import (
    CameraChannel,
    Capture,
    ChannelSpec,
    ControlSink,
    DisplaySink,
    FixedPose,
    FrameSchedule,
    Perceived,
    PerceptionWorker,
    RecorderSink,
    RenderedChannel,
    RobotPose,
    StreamChannel,
)
from hapticloud.hardware.sources import open_source

HIP = np.array([0.1, 0.2, 0.3])


class Clock:
    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class Feed:
    """A robot pose whose time is the clock's (``None`` while ``known`` is False)."""

    def __init__(self, clock: Clock, q=None) -> None:
        self.clock = clock
        self.q = q
        self.known = True

    def read(self):
        return RobotPose(self.clock(), HIP, self.q) if self.known else None


class Fake(CameraChannel):
    """A channel that answers what it is told and remembers how it was asked; ``cost_s``
    advances the clock as rendering would."""

    def __init__(self, spec, clock=None, cost_s=0.0, make=None) -> None:
        super().__init__(spec)
        self.calls: list[tuple[float, RobotPose, object, bool]] = []
        self.clock, self.cost_s = clock, cost_s
        self.make = make or (lambda t: _estimate(t, spec.name))
        self.closed = False

    def capture(self, t_scene, pose, occluders, full_frame):
        self.calls.append((t_scene, pose, occluders, full_frame))
        if self.clock is not None:
            self.clock.now += self.cost_s
        return Capture(self.make(t_scene))

    def close(self) -> None:
        self.closed = True


def _estimate(t: float, camera: str, quality: float = 1.0) -> SurfaceEstimate:
    return SurfaceEstimate(t, camera, np.zeros(3), np.array([0, 0, 1.0]), True, quality=quality)


class Collect:
    wants_frames = False

    def __init__(self) -> None:
        self.items: list[Perceived] = []

    def put(self, item: Perceived) -> None:
        self.items.append(item)


def _worker(channels, clock, *sinks, feed=None, **kw) -> PerceptionWorker:
    return PerceptionWorker(channels, feed or Feed(clock), list(sinks), clock=clock, **kw)


def _run_until(worker: PerceptionWorker, clock: Clock, end: float) -> None:
    """Rounds until ``end``, jumping the clock to each wake time (no sleeping)."""
    while clock.now < end:
        wake = worker.step()
        clock.now = max(clock.now, min(wake, end))


# ----- scheduling --------------------------------------------------------------------------------
def test_schedule_fires_each_camera_on_its_grid_and_the_earliest_first() -> None:
    sched = FrameSchedule([ChannelSpec("a", 10.0), ChannelSpec("b", 10.0, phase_s=0.05)], 0.0)
    assert sched.due(0.0) == 0 and sched.due(-0.01) is None
    sched.advance(0, 0.0)
    assert sched.due(0.06) == 1  # a's next is 0.1
    sched.advance(1, 0.06)
    assert sched.next_t == pytest.approx([0.1, 0.15])
    assert sched.due(0.2) == 0  # both due: the earlier (a at 0.1) first


def test_schedule_skips_and_counts_the_frames_it_could_not_keep_up_with() -> None:
    sched = FrameSchedule([ChannelSpec("a", 10.0)], 5.0)
    sched.advance(0, 5.35)  # frame 0 took until 5.35: frames at 5.1, 5.2, 5.3 are gone
    assert sched.skipped == [3]
    assert sched.next_t[0] == pytest.approx(5.4)


def test_worker_captures_on_the_schedule_with_scene_times_from_the_origin() -> None:
    clock = Clock()
    a = Fake(ChannelSpec("a", 10.0), clock)
    b = Fake(ChannelSpec("b", 10.0, phase_s=0.05), clock)
    sink = Collect()
    w = _worker([a, b], clock, sink)
    w.start(origin=1000.0)
    _run_until(w, clock, 1000.3)
    assert [round(c[0], 6) for c in a.calls] == [0.0, 0.1, 0.2]
    assert [round(c[0], 6) for c in b.calls] == [0.05, 0.15, 0.25]
    assert [i.camera for i in sink.items] == ["a", "b"] * 3
    assert w.stats()["sent"] == {"a": 3, "b": 3}


def test_time_scale_slows_the_schedule_and_the_scene_clock() -> None:
    clock = Clock()
    a = Fake(ChannelSpec("a", 10.0), clock)
    w = _worker([a], clock, time_scale=0.5)
    w.start(origin=1000.0)
    _run_until(w, clock, 1000.45)
    assert [round(c[0], 6) for c in a.calls] == [0.0, 0.1, 0.2]  # every 0.2 s of clock


def test_a_slow_camera_drops_frames_and_counts_them() -> None:
    clock = Clock()
    a = Fake(ChannelSpec("a", 10.0), clock, cost_s=0.25)
    w = _worker([a], clock)
    w.start(origin=1000.0)
    _run_until(w, clock, 1001.0)
    # Each frame takes 0.25 s: captures at 0, 0.3, 0.6, 0.9; the two frames due while each
    # one rendered are skipped (the last capture ends at 1.15: 1.0 and 1.1 are gone too).
    assert [round(c[0], 6) for c in a.calls] == [0.0, 0.3, 0.6, 0.9]
    assert w.stats()["skipped_frames"] == {"a": 8}


def test_no_pose_no_capture_and_the_schedule_goes_on() -> None:
    clock = Clock()
    a = Fake(ChannelSpec("a", 10.0), clock)
    feed = Feed(clock)
    feed.known = False
    w = _worker([a], clock, feed=feed)
    w.start(origin=1000.0)
    _run_until(w, clock, 1000.25)
    feed.known = True
    _run_until(w, clock, 1000.35)
    assert [round(c[0], 6) for c in a.calls] == [0.3]


# ----- time mapping, latency, admission ---------------------------------------------------------
def test_estimates_carry_the_pose_time_and_the_cameras_frame_count() -> None:
    clock = Clock()
    a = Fake(ChannelSpec("a", 10.0), clock, cost_s=0.004)
    sink = Collect()
    w = _worker([a], clock, sink)
    w.start(origin=999.0)  # scene time 1 s at the first capture
    _run_until(w, clock, 1000.15)
    first, second = sink.items
    assert first.captured == 1000.0 and first.estimate.t == 1000.0  # not the render's end
    assert first.t_scene == pytest.approx(1.0) and a.calls[0][0] == pytest.approx(1.0)
    assert (first.seq, second.seq) == (0, 1)
    assert (first.estimate.seq, second.estimate.seq) == (0, 1)
    assert second.captured == pytest.approx(1000.1)


def test_a_free_running_camera_is_stamped_with_its_own_delivery_time() -> None:
    clock = Clock()
    scene = demo_scene(decimation=8)
    src = open_source("simulated", scene=scene, camera="front", realtime=False, clock=clock)

    class Pipe:
        def process_depth(self, frame, hip, exclude=()):
            return SurfaceEstimate.invalid(frame.t, frame.camera, "none", hip=hip)

    ch = StreamChannel(ChannelSpec("front"), src, Pipe())
    sink = Collect()
    w = _worker([ch], clock, sink, feed=FixedPose(HIP, clock=lambda: 1234.0))
    w.start(origin=1000.0)
    assert w.step() == pytest.approx(1000.005)  # nothing yet: look again soon
    src.step()
    clock.now = 1000.002
    src.step()  # the newer frame replaces the unread one
    clock.now = 1000.003
    w.step()
    assert len(sink.items) == 1 and sink.items[0].captured == 1000.003
    assert src.frames_dropped == 1


def test_sinks_get_an_estimate_no_earlier_than_its_latency_after_capture() -> None:
    clock = Clock()
    a = Fake(ChannelSpec("a", 10.0, latency_s=0.005), clock)
    sink = Collect()
    w = _worker([a], clock, sink)
    w.start(origin=1000.0)
    assert w.step() == 1000.0  # captured at 1000.0; more may be due: call again
    assert sink.items == []
    assert w.step() == pytest.approx(1000.005)  # the next thing: the delivery
    clock.now = 1000.004
    w.step()
    assert sink.items == []
    clock.now = 1000.006
    w.step()
    assert len(sink.items) == 1
    assert w.stats()["capture_to_send_ms"]["max"] == pytest.approx(6.0)


def test_admission_follows_the_cameras_quality_and_fallback_rules() -> None:
    clock = Clock()
    quality = iter([0.9, 0.2])
    spec = ChannelSpec("a", 10.0, min_quality=0.5)

    def make(t):
        q = next(quality, None)
        if q is None:  # an empty workspace seen: knowledge of free space, admitted
            return SurfaceEstimate.invalid(t, "a", "empty", hip=HIP, free_m=0.2)
        return SurfaceEstimate(t, "a", np.zeros(3), np.array([0, 0, 1.0]), True, quality=q)

    a = Fake(spec, clock, make=make)
    sink = Collect()
    w = _worker([a], clock, sink)
    w.start(origin=1000.0)
    _run_until(w, clock, 1000.25)
    assert [i.admitted for i in sink.items] == [True, False, True]
    st = w.stats()
    assert st["valid"] == {"a": 2} and st["admitted"] == {"a": 2} and st["sent"] == {"a": 3}


# ----- occluders ---------------------------------------------------------------------------------
def test_occluders_come_from_the_pose_once_and_only_for_cameras_that_see_them() -> None:
    clock = Clock()
    a = Fake(ChannelSpec("a", 10.0), clock)
    oracle = Fake(ChannelSpec("o", 10.0, phase_s=0.05), clock)
    oracle.sees_occluders = False
    asked: list[RobotPose] = []

    def occluders(pose):
        asked.append(pose)
        return ("link", tuple(pose.q))

    sink = Collect()
    w = _worker([a, oracle], clock, sink, feed=Feed(clock, q=np.array([1.0, 2.0])))
    w._occluders = occluders
    w.start(origin=1000.0)
    _run_until(w, clock, 1000.08)
    assert len(asked) == 1
    assert a.calls[0][2] == ("link", (1.0, 2.0)) and oracle.calls[0][2] == ()
    assert sink.items[0].occluders == ("link", (1.0, 2.0))


def test_rendered_channel_crops_unless_a_sink_keeps_whole_frames() -> None:
    scene = demo_scene(decimation=8)
    cam = scene.cameras[0]
    hip = np.asarray(cam.origin_world) + 0.6 * np.asarray(cam.axis_world)

    def frames(*sinks):
        clock = Clock()
        src = open_source("simulated", camera=cam, world=scene.world, realtime=False)
        ch = RenderedChannel(ChannelSpec(cam.name), src, CameraPipeline(camera=cam.name))
        seen = Collect()
        w = _worker([ch], clock, seen, *sinks, feed=FixedPose(hip, clock=clock))
        w.start(origin=1000.0)
        w.step()
        assert src.frames_received == 1  # read back through the source
        return seen.items[0].frame

    cropped, whole = frames(), frames(RecorderSink(_RecordSink()))
    assert 0 < np.count_nonzero(cropped.depth_m) < np.count_nonzero(whole.depth_m)


# ----- sinks -------------------------------------------------------------------------------------
class _RecordSink:
    dropped = 2

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def capture(self, *args):
        self.calls.append(("capture", *args))

    def estimate(self, *args):
        self.calls.append(("estimate", *args))


def _item(frame=None) -> Perceived:
    est = SurfaceEstimate(5.0, "a", np.zeros(3), np.array([0, 0, 1.0]), True, quality=0.7, seq=3)
    return Perceived("a", 3, 1.0, 5.0, est, frame, HIP, None, ("link",), True, 1.0)


def test_control_sink_sends_the_one_wire_form_and_goes_quiet_when_the_pipe_is_gone() -> None:
    recv, send = mp.Pipe(duplex=False)
    sink = ControlSink(send)
    sink.put(_item())
    kind, wire = recv.recv()
    got = estimate_from_wire(wire)
    assert kind == "estimate" and got.t == 5.0 and got.seq == 3 and got.quality == 0.7
    recv.close()
    sink.put(_item())
    assert not sink.alive and sink.sent == 1
    sink.put(_item())  # quiet, no error


def test_control_sink_can_drop_instead_of_waiting_for_a_full_pipe() -> None:
    recv, send = mp.Pipe(duplex=False)
    sink = ControlSink(send, drop_when_full=True)
    for _ in range(20000):  # far more than a pipe's buffer
        sink.put(_item())
        if sink.dropped:
            break
    assert sink.dropped == 1 and sink.alive
    recv.close()


def test_display_sink_takes_a_callback_or_a_queue_and_counts_what_a_full_queue_drops() -> None:
    got: list[Perceived] = []
    DisplaySink(got.append).put(_item())
    assert len(got) == 1
    q: queue.Queue = queue.Queue(maxsize=1)
    sink = DisplaySink(q)
    sink.put(_item())
    sink.put(_item())
    assert q.qsize() == 1 and sink.dropped == 1


def test_recorder_sink_records_frames_and_frameless_estimates_only_when_asked() -> None:
    rec = _RecordSink()
    RecorderSink(rec).put(_item(frame="F"))
    RecorderSink(rec).put(_item())
    RecorderSink(rec, frameless=True).put(_item())
    kinds = [c[0] for c in rec.calls]
    assert kinds == ["capture", "estimate"]
    assert rec.calls[0][1:4] == (5.0, "F", HIP) and rec.calls[0][4] == ("link",)
    assert RecorderSink(rec).dropped == 2


def test_stats_name_what_each_sink_dropped() -> None:
    clock = Clock()
    w = _worker([Fake(ChannelSpec("a"), clock)], clock, RecorderSink(_RecordSink()), Collect())
    w.start()
    assert w.stats()["sink_dropped"] == {"RecorderSink": 2}


# ----- running -----------------------------------------------------------------------------------
def test_the_worker_runs_in_a_thread_until_stopped_and_closes_its_channels() -> None:
    a = Fake(ChannelSpec("a", 200.0))
    got = threading.Event()
    sink = DisplaySink(lambda item: got.set() if item.seq >= 3 else None)
    w = PerceptionWorker([a], FixedPose(HIP), [sink])
    w.start_thread()
    assert got.wait(5.0)
    w.close()
    n = len(a.calls)
    time.sleep(0.05)
    assert len(a.calls) == n and a.closed and not w.errors


def test_a_failing_channel_ends_the_thread_with_its_error() -> None:
    def boom(t):
        raise RuntimeError("render failed")

    w = PerceptionWorker([Fake(ChannelSpec("a", 200.0), make=boom)], FixedPose(HIP))
    w.start_thread()
    deadline = time.monotonic() + 5.0
    while not w.errors and time.monotonic() < deadline:
        time.sleep(0.01)
    w.stop_thread()
    assert w.errors and "render failed" in w.errors[0]


def test_bad_arguments_are_refused() -> None:
    clock = Clock()
    with pytest.raises(ValueError, match="unique"):
        _worker([Fake(ChannelSpec("a")), Fake(ChannelSpec("a"))], clock)
    with pytest.raises(ValueError, match="time_scale"):
        _worker([Fake(ChannelSpec("a"))], clock, time_scale=math.nan)
    with pytest.raises(RuntimeError, match="start"):
        _worker([Fake(ChannelSpec("a"))], clock).step()


def test_the_bench_runs_both_cameras_through_the_worker_in_a_thread() -> None:
    from hapticloud.hardware.control.bench import _perception_figures, bench_perception

    worker = bench_perception(None, decimation=8)
    try:
        deadline = time.monotonic() + 10.0
        while min(worker.stats()["sent"].values()) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        worker.close()
    fig = _perception_figures(worker)
    assert min(fig["frames_processed"]) >= 2 and fig["errors"] == []
    assert worker.camera_names == ["front", "right45"]
