"""hardware/live (no Qt): frozen numbered snapshots, config requests, emergency stop."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from hapticloud.core.errors import ConfigError
from hapticloud.hardware.live.contract import FRAME_COLUMNS, TICK_COLUMNS, LiveConfig, SourceState
from hapticloud.hardware.live.scenes import SimSettings
from hapticloud.hardware.live.source import LiveSource

# 424x240 cameras: the same scene, four times cheaper to simulate (tests share 2 cores).
FAST = SimSettings(decimation=2)


def _wait(predicate, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("timed out")
        time.sleep(0.01)


@pytest.fixture(scope="module")
def source():
    src = LiveSource(FAST)
    src.start()
    _wait(lambda: (s := src.latest()) is not None and s.seq >= 8)
    yield src
    src.close()


def test_snapshots_are_numbered_frozen_and_complete(source: LiveSource) -> None:
    first = source.latest()
    _wait(lambda: source.latest().seq > first.seq + 3)
    snap = source.latest()
    assert snap.seq > first.seq and snap.t > first.t
    assert snap.state is SourceState.RUNNING
    assert [c.name for c in snap.cameras] == [c.name for c in source.geometry.cameras]
    assert snap.history.frames.shape[1] == len(FRAME_COLUMNS)
    assert snap.history.ticks.shape[1] == len(TICK_COLUMNS)
    # Control ticks at 800 Hz between camera frames: many more rows than frames.
    assert len(snap.history.ticks) > 5 * len(snap.history.frames)
    for array in (snap.hip, snap.history.frames, snap.cameras[0].context):
        with pytest.raises(ValueError):
            array[0] = 0  # read-only: the GUI cannot alter what the worker published
    assert snap.truth is not None and len(snap.body_offsets) == len(source.geometry.bodies)


@pytest.mark.skipif(not hasattr(os, "sched_getscheduler"), reason="Linux scheduling only")
def test_the_worker_process_runs_its_frames_real_time_and_a_worker_thread_does_not() -> None:
    """In a process of its own the worker takes SCHED_FIFO below the control loop once built
    (root) or nice -5 (refused); on the window's thread it stays a normal thread."""
    from hapticloud.hardware.live.worker import WORKER_FIFO_PRIORITY, WORKER_NICE

    src = LiveSource(FAST)
    src.start()
    try:
        _wait(lambda: src.latest() is not None)
        pid = src._worker.pid
        if os.geteuid() == 0:
            assert os.sched_getscheduler(pid) == os.SCHED_FIFO
            assert os.sched_getparam(pid).sched_priority == WORKER_FIFO_PRIORITY < 80
        else:
            assert os.sched_getscheduler(pid) != os.SCHED_FIFO
    finally:
        src.close()
    src = LiveSource(FAST, in_process=True)
    src.start()
    try:
        _wait(lambda: src.latest() is not None)
        tid = src._worker.native_id
        assert os.sched_getscheduler(tid) != os.SCHED_FIFO
        if os.geteuid() == 0:
            assert os.getpriority(os.PRIO_PROCESS, tid) == WORKER_NICE
    finally:
        src.close()


def test_config_request_reaches_the_pipelines(source: LiveSource) -> None:
    config = source.requested_config.replace_path("perception.voxel.voxel_size_m", 0.006)
    version = source.request_config(config)
    _wait(lambda: source.latest().config_version == version)
    # Read back from the worker's pipelines, not echoed from the request.
    assert source.latest().config.perception.voxel.voxel_size_m == 0.006


def test_only_built_configs_are_accepted(source: LiveSource) -> None:
    with pytest.raises(ConfigError):
        source.request_config({"perception": {}})  # type: ignore[arg-type]


def test_bad_settings_are_refused_with_a_reason() -> None:
    with pytest.raises(ConfigError, match="nowhere: no such scene file"):
        SimSettings(scene="nowhere")
    with pytest.raises(ConfigError, match="decimation"):
        SimSettings(decimation=3)


def test_emergency_stop_ends_the_worker_within_a_frame() -> None:
    src = LiveSource(FAST, LiveConfig())
    src.start()
    try:
        _wait(lambda: src.latest() is not None)
        t0 = time.monotonic()
        src.emergency_stop("test")
        _wait(lambda: src.state is SourceState.STOPPED, timeout_s=2.0)
        assert time.monotonic() - t0 < 0.5
        last = src.latest()
        assert last.state is SourceState.STOPPED and last.message == "test"
        seq = last.seq
        time.sleep(0.2)
        assert src.latest().seq == seq  # nothing after the stop
    finally:
        src.close()
    assert not src.alive


def test_errors_against_truth_are_small_on_the_demo(source: LiveSource) -> None:
    snap = source.latest()
    errors = snap.history.frame("error_mm")
    valid = errors[np.isfinite(errors)]
    assert len(valid) > 5
    assert float(np.median(valid)) < 10.0


def test_a_session_robot_fills_the_geometry_slots_with_the_links():
    from hapticloud.core.geometry.primitives import Capsule, Sphere
    from hapticloud.core.robot import RobotModel
    from hapticloud.hardware.live.scenes import SimSettings, scene_geometry, session_robot

    model = RobotModel.load()
    q = model.q_home
    hip = model.hip_position_at(q)
    robot = session_robot(hip, q)
    geometry = scene_geometry(SimSettings())
    assert isinstance(robot[0], Sphere) and np.allclose(robot[0].center, hip)
    assert all(isinstance(p, Capsule) for p in robot[1:])
    assert len(robot) == 1 + len(model.capsule_specs) <= len(geometry.robot_shapes)
    assert geometry.robot_shapes[: len(robot)] == ("sphere",) + ("capsule",) * (len(robot) - 1)


def test_scene_files_open_in_the_app_and_bad_ones_say_why():
    from hapticloud.core.errors import ConfigError
    from hapticloud.hardware.live.scenes import SimSettings, scene_spec

    spec = scene_spec("impacts")  # a shipped scene file
    scene = spec.build(decimation=4)
    assert [c.name for c in scene.cameras] == ["front", "right45"]
    assert scene.world.bodies and np.isfinite(spec.hip_path(0.0)).all()
    assert SimSettings(scene="impacts").scene == "impacts"
    with pytest.raises(ConfigError) as err:
        SimSettings(scene="no-such-scene")
    assert "no-such-scene" in str(err.value) and "\n" not in str(err.value)


def test_each_camera_sends_its_scene_cloud_at_most_every_context_period() -> None:
    """The scene cloud is a picture of the room: rendered and sent every CONTEXT_PERIOD_S per
    camera, the frames between carry none, and every snapshot shows the camera's last one."""
    import dataclasses
    import queue
    import threading

    from hapticloud.hardware.live import worker as live_worker
    from hapticloud.hardware.live.session import scene_tables

    class Conn:
        def __init__(self) -> None:
            self.packets: list = []

        def send(self, packet) -> None:
            self.packets.append(packet)

    conn = Conn()
    config = dataclasses.replace(LiveConfig(), **scene_tables("demo"))
    w = live_worker._Worker(FAST, config, conn, queue.Queue(), threading.Event())
    w.perception.start()
    deadline = time.monotonic() + 20.0
    while len(conn.packets) < 40 and time.monotonic() < deadline:
        time.sleep(max(0.0, w.perception.step() - time.monotonic()))
    w.perception.close()
    assert len(conn.packets) >= 40
    for j in range(len(w.display.channels)):
        mine = [p for p in conn.packets if p.camera == j]
        sent = [p.t for p in mine if p.context is not None]
        assert mine[0].context is not None and len(mine[0].context) > 100
        assert 1 < len(sent) < len(mine)  # some frames carry one, most do not
        assert np.all(np.diff(sent) >= live_worker.CONTEXT_PERIOD_S - 1e-9)
        # Never longer without one than the period plus a frame.
        assert np.all(np.diff(sent) < live_worker.CONTEXT_PERIOD_S + 0.07)
    # The receiver keeps the last cloud of each camera for the frames without one.
    from hapticloud.hardware.live.source import _Receiver

    cameras = len(w.display.channels)
    src, state = LiveSource(FAST), _Receiver(cameras)
    snaps = [src._compose(state, p) for p in conn.packets]
    for snap in snaps[cameras:]:
        for frame in snap.cameras:
            assert len(frame.context) > 100 and not frame.context.flags.writeable


def test_the_scene_cloud_is_rendered_only_while_the_window_shows_it() -> None:
    """A ContextRequest(False) (the window's context layer hidden, its default) stops the
    worker rendering the scene clouds; True brings them back at the next due frame."""
    import dataclasses
    import queue
    import threading

    from hapticloud.hardware.live import worker as live_worker
    from hapticloud.hardware.live.session import scene_tables

    class Conn:
        def __init__(self) -> None:
            self.packets: list = []

        def send(self, packet) -> None:
            self.packets.append(packet)

    conn, requests = Conn(), queue.Queue()
    config = dataclasses.replace(LiveConfig(), **scene_tables("demo"))
    w = live_worker._Worker(FAST, config, conn, requests, threading.Event())
    renders = []
    for twin in w.display.twins:
        original = twin.render
        twin.render = lambda *a, _o=original, **k: renders.append(1) or _o(*a, **k)

    def run_until(n: int) -> None:
        deadline = time.monotonic() + 20.0
        while len(conn.packets) < n and time.monotonic() < deadline:
            w._apply_requests()
            time.sleep(max(0.0, w.perception.step() - time.monotonic()))

    requests.put(live_worker.ContextRequest(False))
    w.perception.start()
    try:
        run_until(30)
        assert len(conn.packets) >= 30
        assert renders == [] and all(p.context is None for p in conn.packets)
        requests.put(live_worker.ContextRequest(True))
        run_until(60)
    finally:
        w.perception.close()
    assert renders and any(p.context is not None for p in conn.packets[30:])
