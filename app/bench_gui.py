"""``hapticloud bench gui``: how fast the 3D view updates, and how late a frame reaches the screen.

The :class:`~hapticloud.app.scene_view.SceneView` (880x500 px, its size in a 1280x800 window) is
built on the demo scene's geometry and fed synthetic snapshots, a new one per update: two
5000-point clouds (a noisy curved patch under the moving HIP per camera, plus 300 "filled"
points; the snapshots also carry 5000 cropped context points per camera, a layer off by default
as in the app), four paper-method shells per camera (circles and normals, one rejected), both
cameras' estimates, the fused centroid and normal (the arrow), the true closest
point, the robot and the true surface. Nothing is simulated: the figures are the view's alone.

One update is: build the snapshot (its ``captured`` time is taken then), ``show_snapshot`` (the
in-place actor update, timed), then the event loop runs until the paint it scheduled has
returned (the VTK render, its read-back and its drawing, timed). Frame-to-screen latency is from
the snapshot's ``captured`` time to the end of that paint; frame-to-flush also includes the rest
of that event-loop turn (Qt flushes the window's painted region to X).
Updates per second are counted in 1 s windows of wall time after a short warm-up; the median
window is reported.

The view is measured alone first, then again while the control process runs on the same cores
(``with_control_*``). The control process (the demo scene, 800 Hz, six emulated drives in their
own process, as the app runs it:
:data:`~hapticloud.hardware.live.session.APP_PROCESS_KWARGS`; idle in READY: drive bus I/O and
the tick run, no torque) is measured twice in the same run for the same
duration: alone (no GUI), then while the view is updated at full speed. Both report deadline
misses per 10,000 ticks (:class:`~hapticloud.hardware.control.DeadlineLoop`'s statistics).
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
import time
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

if TYPE_CHECKING:
    from hapticloud.hardware.live.contract import Snapshot

N_POINTS = 5000
N_FILLED = 300
N_SHELLS = 4
VIEW_SIZE = (880, 500)  # the 3D view's size in a 1280x800 window
WARMUP_UPDATES = 5


def _ms(values: list[float], q: float) -> float:
    return round(1e3 * float(np.percentile(values, q)), 2) if values else float("nan")


class _Frames:
    """Synthetic snapshots on the demo scene's geometry, moving with time."""

    def __init__(self, seed: int = 0) -> None:
        from hapticloud.hardware.live.contract import (
            FRAME_COLUMNS,
            TICK_COLUMNS,
            History,
            LiveConfig,
        )
        from hapticloud.hardware.live.scenes import (
            SimSettings,
            robot_at,
            scene_geometry,
            scene_spec,
        )

        self.settings = SimSettings(decimation=2)
        self.geometry = scene_geometry(self.settings)
        self._hip_path = scene_spec(self.settings.scene).hip_path
        self._robot_at = robot_at
        self._config = LiveConfig()
        self._history = History(np.zeros((0, len(FRAME_COLUMNS))), np.zeros((0, len(TICK_COLUMNS))))
        self._rng = np.random.default_rng(seed)
        self.seq = 0

    def snapshot(self, t: float) -> Snapshot:
        from hapticloud.core.fusion import FusedSurface
        from hapticloud.core.perception import ShellFit, SurfaceEstimate
        from hapticloud.core.sim import GroundTruth
        from hapticloud.hardware.live.contract import CameraFrame, Snapshot, SourceState

        captured = time.monotonic()
        rng = self._rng
        hip = np.asarray(self._hip_path(t), dtype=np.float64)
        # The surface under the HIP: normal towards the HIP, tilting slowly with time.
        normal = np.array([1.0, 0.3 * math.sin(t), 0.2 * math.cos(0.7 * t)])
        normal /= np.linalg.norm(normal)
        surface = hip - 0.05 * normal
        helper = np.array([0.0, 0.0, 1.0])
        u = np.cross(normal, helper)
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        cameras = []
        for k, cam in enumerate(self.geometry.cameras):
            ab = rng.uniform(-0.1, 0.1, (N_POINTS, 2))
            bulge = -2.0 * (ab**2).sum(axis=1, keepdims=True)  # a curved patch
            points = surface + ab[:, :1] * u + ab[:, 1:] * v + bulge * normal
            points += rng.normal(0.0, 0.001, points.shape)
            centroid = surface + 0.002 * k * u
            shells = tuple(
                ShellFit(
                    0.04 + 0.02 * i,
                    0.06 + 0.02 * i,
                    "circle" if i else "plane",
                    centroid - 0.004 * i * normal,
                    normal,
                    60,
                    True,
                    i % 2 == 0,
                    0.03 + 0.01 * i,
                )
                for i in range(N_SHELLS)
            )
            est = SurfaceEstimate(
                t,
                cam.name,
                centroid,
                normal,
                True,
                method="paper",
                hip=hip,
                n_points=N_POINTS,
                shells=shells,
                points=points,
                filled=points[:N_FILLED] + 0.002 * normal,
                seq=self.seq,
            )
            context = (
                surface + rng.uniform(-0.3, 0.3, (N_POINTS, 3)) * np.array([0.2, 1.0, 1.0])
            ).astype(np.float32)
            cameras.append(CameraFrame(cam.name, est, context, 5.0, 30.0, 0.05, 1.0, 2.0))
        zero = np.zeros(3)
        fused = FusedSurface(
            t,
            surface,
            normal,
            True,
            zero,
            surface,
            normal,
            0.01,
            False,
            "",
            40,
            2,
            tuple(c.name for c in self.geometry.cameras),
            self.seq,
        )
        truth = GroundTruth(surface - 0.001 * normal, normal, 0.05, "torso", "chest")
        snap = Snapshot(
            seq=self.seq,
            t=t,
            published=time.monotonic(),
            captured=captured,
            state=SourceState.RUNNING,
            message="",
            hip=hip,
            robot=self._robot_at(self.settings, hip),
            cameras=tuple(cameras),
            fused=fused,
            fused_d_proj_m=0.05,
            truth=truth,
            body_offsets=tuple(np.zeros(3) for _ in self.geometry.bodies),
            config=self._config,
            config_version=0,
            real_time_factor=1.0,
            history=self._history,
        )
        self.seq += 1
        return snap


def measure(duration_s: float) -> dict[str, float | int]:
    """Run the view at full speed for ``duration_s`` seconds (needs a QApplication)."""
    from hapticloud.app.scene_view import SceneView
    from PyQt6 import QtWidgets

    app = QtWidgets.QApplication.instance()
    assert app is not None
    frames = _Frames()
    view = SceneView()
    view.resize(*VIEW_SIZE)
    view.set_geometry(frames.geometry)
    view.show()
    # The app's default layers: everything on except the cropped scene points ("context", two
    # more 5000-point clouds, off by default; the snapshots carry them as the live source does).
    for key in ("clouds", "bodies", "truth", "robot", "shells", "estimates", "fused"):
        view.set_layer_visible(key, True, render=False)

    paints: list[tuple[float, float]] = []  # (start, end) of each paint, perf_counter

    def timed_paint(start: float, end: float) -> None:
        paints.append((start, end))

    view.canvas.on_paint.append(timed_paint)
    try:
        deadline = time.monotonic() + 10.0
        while not view.canvas.isVisible() and time.monotonic() < deadline:
            app.processEvents()
        view.show_snapshot(frames.snapshot(0.0))
        while not paints and time.monotonic() < deadline:
            app.processEvents()
        if not paints:
            raise RuntimeError("the 3D view never painted (no OpenGL on this display?)")
        actors_before = view.actor_count()

        update_s: list[float] = []
        render_s: list[float] = []
        latency_s: list[float] = []
        flush_s: list[float] = []
        shown_at: list[float] = []
        t0 = time.perf_counter()
        end = t0 + duration_s
        k = 0
        while True:
            now = time.perf_counter()
            if now >= end and k > WARMUP_UPDATES:
                break
            want = len(paints) + 1
            snap = frames.snapshot(0.033 * (k + 1))
            a = time.perf_counter()
            view.show_snapshot(snap)
            b = time.perf_counter()
            while len(paints) < want:
                app.processEvents()
            flushed = time.monotonic()  # the turn that painted also composited and flushed it
            start, stop = paints[-1]
            # captured is time.monotonic(); convert the paint's end to that clock.
            stop_mono = time.monotonic() - (time.perf_counter() - stop)
            if k >= WARMUP_UPDATES:
                update_s.append(b - a)
                render_s.append(stop - start)
                latency_s.append(stop_mono - snap.captured)
                flush_s.append(flushed - snap.captured)
                shown_at.append(stop)
            k += 1
        actors_added = view.actor_count() - actors_before
    finally:
        view.canvas.on_paint.remove(timed_paint)
        view.close_view()
        view.deleteLater()
        app.processEvents()

    t_first = shown_at[0] if shown_at else t0
    span = (shown_at[-1] - t_first) if shown_at else 0.0
    windows = int(span)  # whole 1 s windows
    if windows >= 1:
        edges = t_first + np.arange(windows + 1)
        counts = np.histogram(shown_at, bins=edges)[0]
        per_s = float(np.median(counts))
    else:
        per_s = (len(shown_at) - 1) / span if span > 0 else 0.0
    return {
        "updates_per_s": round(per_s, 1),
        "updates": len(update_s),
        "duration_s": round(span, 2),
        "update_ms_median": _ms(update_s, 50),
        "update_ms_p90": _ms(update_s, 90),
        "render_ms_median": _ms(render_s, 50),
        "render_ms_p90": _ms(render_s, 90),
        "frame_to_screen_ms_median": _ms(latency_s, 50),
        "frame_to_screen_ms_p90": _ms(latency_s, 90),
        "frame_to_flush_ms_median": _ms(flush_s, 50),
        "frame_to_flush_ms_p90": _ms(flush_s, 90),
        "actors_added": int(actors_added),
        "view_px": f"{VIEW_SIZE[0]}x{VIEW_SIZE[1]}",
        "points_per_cloud": N_POINTS,
    }


def _control(duration_s: float, during: Any = None) -> dict[str, Any]:
    """Run the demo's control process for ``duration_s`` (or while ``during()`` runs)."""
    from hapticloud.hardware.control import ControlProcess
    from hapticloud.hardware.live.session import APP_PROCESS_KWARGS

    cp = ControlProcess("demo", emulator="process", **APP_PROCESS_KWARGS)
    cp.start()
    try:
        out = during() if during is not None else time.sleep(duration_s)
    finally:
        result = cp.stop() or {}
    stats = result.get("deadline", {})
    return {
        "ticks": int(result.get("ticks", 0)),
        "misses": int(stats.get("misses", 0)),
        "misses_per_10k": round(float(stats.get("misses_per_10k", math.nan)), 2),
        "work_us_p99": round(float(stats.get("work_us_p99", math.nan)), 1),
        "sched_fifo": bool(stats.get("sched_fifo", False)),
        "during": out,
    }


def _run_app(duration_s: float, control: bool = True) -> dict[str, Any]:
    from PyQt6 import QtWidgets, sip

    created = QtWidgets.QApplication.instance() is None
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv[:1])
    try:
        # The view alone first (the figure), then again while the control process runs
        # on the same cores (what a session costs the view, and the loop's misses with a GUI).
        result = measure(duration_s)
        if not control:
            return result
        run = _control(duration_s, lambda: measure(duration_s))
        during = run.pop("during")
        for key in ("updates_per_s", "render_ms_median", "frame_to_screen_ms_median"):
            result[f"with_control_{key}"] = during[key]
        result.update({f"control_gui_{k}": v for k, v in run.items()})
        return result
    finally:
        if created:
            # Destroy Qt's objects while the display still exists (a virtual one stops next).
            app.processEvents()
            sip.delete(app)


def main(
    duration_s: float,
    as_json: bool,
    out: TextIO,
    display: contextlib.AbstractContextManager[object],
) -> int:
    """Measure and print the figures; the window shows on ``display`` (entered after the
    control process was measured alone)."""
    alone = _control(duration_s)
    alone.pop("during")
    with display:
        result = _run_app(duration_s)
    result.update({f"control_alone_{k}": v for k, v in alone.items()})
    if as_json:
        print(json.dumps(result), file=out)
    else:
        print(
            f"3D view, {result['view_px']} px, 2 x {N_POINTS} points and every overlay, "
            f"{result['updates']} updates in {result['duration_s']} s\n"
            f"  updates/s (median of 1 s windows): {result['updates_per_s']}  (target >= 30)\n"
            f"  actor update: {result['update_ms_median']} ms median, "
            f"{result['update_ms_p90']} ms p90\n"
            f"  render (paint): {result['render_ms_median']} ms median, "
            f"{result['render_ms_p90']} ms p90\n"
            f"  frame-to-screen: {result['frame_to_screen_ms_median']} ms median, "
            f"{result['frame_to_screen_ms_p90']} ms p90 (to the end of the paint)\n"
            f"  frame-to-flush: {result['frame_to_flush_ms_median']} ms median, "
            f"{result['frame_to_flush_ms_p90']} ms p90 (to the end of the event-loop turn that "
            "painted: Qt's flush to X included)\n"
            f"  actors added during updates: {result['actors_added']}\n"
            f"  with the control process running too: {result['with_control_updates_per_s']} "
            f"updates/s, render {result['with_control_render_ms_median']} ms median, "
            f"frame-to-screen {result['with_control_frame_to_screen_ms_median']} ms median\n"
            f"control process (demo, 800 Hz, 6 emulated drives in their own process), "
            f"{duration_s:g} s each:\n"
            f"  no GUI:        {result['control_alone_misses_per_10k']} misses per 10k ticks "
            f"({result['control_alone_misses']} of {result['control_alone_ticks']}), "
            f"work p99 {result['control_alone_work_us_p99']} us\n"
            f"  with the GUI:  {result['control_gui_misses_per_10k']} misses per 10k ticks "
            f"({result['control_gui_misses']} of {result['control_gui_ticks']}), "
            f"work p99 {result['control_gui_work_us_p99']} us",
            file=out,
        )
    return 0 if result["actors_added"] == 0 else 1
