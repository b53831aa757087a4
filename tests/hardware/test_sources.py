"""Camera sources: the registry, deterministic stepping, timeouts, the render thread, drops."""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
import pytest
from hapticloud.core.camera import DepthFrame
from hapticloud.core.errors import SourceError
from hapticloud.core.sim import SimScene, demo_scene
from hapticloud.hardware.sources import CameraSource, base, open_source, register_source
from hapticloud.hardware.sources.simulated import SimulatedCameraSource, simulated_pair

SLACK_S = 0.05


@pytest.fixture(scope="module")
def scene() -> SimScene:
    return demo_scene(decimation=4)


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


# ----- registry ----------------------------------------------------------------------------------
def test_unknown_kind_names_it_and_the_known_kinds() -> None:
    with pytest.raises(SourceError, match=r"'webcam'.*known: .*realsense, simulated"):
        open_source("webcam")


def test_realsense_fails_only_when_chosen(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails even if installed
    with pytest.raises(SourceError) as info:
        open_source("realsense", serial="123")
    assert str(info.value) == "realsense: pyrealsense2 is not installed (pip install pyrealsense2)"


def test_register_source(monkeypatch: pytest.MonkeyPatch, scene: SimScene) -> None:
    monkeypatch.setattr(base, "_FACTORIES", dict(base._FACTORIES))
    monkeypatch.setattr(base, "_LAZY", dict(base._LAZY))
    made = []

    def factory(**kwargs: object) -> CameraSource:
        made.append(kwargs)
        return SimulatedCameraSource(scene.cameras[0], scene.world, realtime=False)

    register_source("recording", factory)
    assert "recording" in base.known_kinds()
    with open_source("recording", path="x.h5") as src:
        assert src.name == "front"
    assert made == [{"path": "x.h5"}]


def test_open_simulated_by_scene_and_camera_name(scene: SimScene) -> None:
    with open_source("simulated", scene=scene, camera="right45", realtime=False) as src:
        assert isinstance(src, SimulatedCameraSource)
        assert src.step().camera == "right45"
    with pytest.raises(SourceError, match=r"simulated: .*'nope'"):
        open_source("simulated", scene=scene, camera="nope", realtime=False)


# ----- deterministic stepping ------------------------------------------------------------------
def test_stepping_pair_interleaves_at_the_right_times(scene: SimScene) -> None:
    clock = FakeClock()
    front, right = simulated_pair(scene, rate_hz=30.0, clock=clock, realtime=False)
    assert (front.name, right.name) == ("front", "right45")
    assert front.thread is None and right.thread is None
    got = []
    for _ in range(3):
        for src in (front, right):
            src.step()
            clock.now += 0.01
            frame = src.read(0.0)
            assert isinstance(frame, DepthFrame)
            assert frame.camera == src.name
            assert frame.depth_m.shape == (120, 212)
            assert src.last_frame_time == pytest.approx(clock.now)
            got.append(frame.t)
    period = 1 / 30
    expected = [k * period + phase for k in range(3) for phase in (0.0, period / 2)]
    np.testing.assert_allclose(got, expected, atol=1e-12)
    assert front.frames_received == right.frames_received == 3
    assert front.frames_dropped == 0


def test_stepping_is_deterministic(scene: SimScene) -> None:
    a = SimulatedCameraSource(scene.cameras[0], scene.world, realtime=False)
    b = SimulatedCameraSource(scene.cameras[0], scene.world, realtime=False)
    fa, fb = a.step(), b.step()
    np.testing.assert_array_equal(fa.depth_m, fb.depth_m)
    assert np.count_nonzero(fa.depth_m) > 0


def test_occluders_at_is_called_with_frame_time(scene: SimScene) -> None:
    times: list[float] = []

    def occluders_at(t: float) -> tuple:
        times.append(t)
        return ()

    src = SimulatedCameraSource(
        scene.cameras[0], scene.world, occluders_at, rate_hz=10.0, phase_s=0.2, realtime=False
    )
    src.step()
    src.step()
    np.testing.assert_allclose(times, [0.2, 0.3])


def test_drops_counted_when_nobody_reads(scene: SimScene) -> None:
    src = SimulatedCameraSource(scene.cameras[0], scene.world, realtime=False)
    frames = [src.step() for _ in range(4)]
    assert src.frames_dropped == 3
    assert src.read(0.0) is frames[-1]  # the newest replaces unread older ones
    assert src.read(0.0) is None
    assert src.frames_received == 1


def test_step_needs_stepping_mode(scene: SimScene) -> None:
    with SimulatedCameraSource(scene.cameras[0], scene.world, rate_hz=1.0, phase_s=5.0) as src:
        with pytest.raises(SourceError, match="realtime=False"):
            src.step()


# ----- timeouts ----------------------------------------------------------------------------------
@pytest.mark.parametrize("realtime", [False, True])
def test_read_returns_none_in_time(scene: SimScene, realtime: bool) -> None:
    # the threaded source's first frame is 5 s away: nothing arrives within the timeout
    with SimulatedCameraSource(
        scene.cameras[0], scene.world, rate_hz=1.0, phase_s=5.0, realtime=realtime
    ) as src:
        for timeout in (0.0, 0.1):
            t0 = time.monotonic()
            assert src.read(timeout) is None
            assert time.monotonic() - t0 < timeout + SLACK_S
        assert src.frames_received == 0 and src.last_frame_time is None


def test_bad_timeout_rejected(scene: SimScene) -> None:
    with SimulatedCameraSource(scene.cameras[0], scene.world, realtime=False) as src:
        for bad in (-1.0, float("nan"), float("inf")):
            with pytest.raises(SourceError, match="timeout"):
                src.read(bad)


# ----- the render thread -------------------------------------------------------------------------
def test_thread_delivers_frames_and_close_stops_it(scene: SimScene) -> None:
    src = SimulatedCameraSource(scene.cameras[0], scene.world, rate_hz=30.0)
    thread = src.thread
    assert thread is not None and thread.daemon and thread.name == "hapticloud-camera-front"
    times = []
    for _ in range(4):
        frame = src.read(1.0)
        assert frame is not None and frame.camera == "front"
        times.append(frame.t)
    assert times == sorted(times) and len(set(times)) == 4
    assert src.frames_received == 4
    assert src.last_frame_time is not None and src.last_frame_time <= time.monotonic()
    src.close()
    thread.join(timeout=2.0)
    assert not thread.is_alive()
    assert thread not in threading.enumerate()


def test_thread_counts_drops_when_nobody_reads(scene: SimScene) -> None:
    with SimulatedCameraSource(scene.cameras[0], scene.world, rate_hz=60.0) as src:
        deadline = time.monotonic() + 3.0
        while src.frames_produced < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        produced = src.frames_produced
        assert produced >= 4
        assert src.frames_dropped >= produced - 2  # at most one more published since
        assert src.read(1.0) is not None


def test_render_failure_reaches_the_reader(scene: SimScene) -> None:
    def broken(t: float) -> tuple:
        raise ValueError("robot model missing")

    with SimulatedCameraSource(scene.cameras[0], scene.world, broken, rate_hz=30.0) as src:
        with pytest.raises(SourceError, match="front: rendering failed: robot model missing"):
            src.read(1.0)


# ----- close -------------------------------------------------------------------------------------
@pytest.mark.parametrize("realtime", [False, True])
def test_close_is_idempotent_and_reads_after_close_fail(scene: SimScene, realtime: bool) -> None:
    src = SimulatedCameraSource(scene.cameras[0], scene.world, realtime=realtime)
    src.close()
    src.close()
    assert src.closed
    with pytest.raises(SourceError, match="front: read from a closed source"):
        src.read(0.0)
    if src.thread is not None:
        assert not src.thread.is_alive()


def test_context_manager_closes(scene: SimScene) -> None:
    with SimulatedCameraSource(scene.cameras[0], scene.world, realtime=False) as src:
        assert not src.closed
    assert src.closed
