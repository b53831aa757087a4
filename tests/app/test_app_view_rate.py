"""How fast the 3D view updates: two 5000-point clouds and every overlay (a benchmark: ``slow``).

Snapshots come from the live demo, their clouds resampled to 5000 points per camera and four
paper-method shells added per camera; each update is ``show_snapshot`` followed by the one
paint it schedules (measured until the paint returned). Run with
``pytest -m slow tests/app/test_app_view_rate.py -s`` to see the figures.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
from hapticloud.app.scene_view import SceneView
from hapticloud.core.perception import ShellFit
from hapticloud.hardware.live.contract import Snapshot
from hapticloud.hardware.live.scenes import SimSettings
from hapticloud.hardware.live.source import LiveSource

N_POINTS = 5000
N_UPDATES = 150


def _snapshots(count: int) -> tuple[object, list[Snapshot]]:
    source = LiveSource(SimSettings(decimation=2), in_process=True)
    source.start()
    snaps: list[Snapshot] = []
    deadline = time.monotonic() + 30
    while len(snaps) < count and time.monotonic() < deadline:
        snap = source.latest()
        ok = snap is not None and len(snap.cameras) == 2
        ok = ok and all(
            c.estimate.points is not None and len(c.estimate.points) for c in snap.cameras
        )
        if ok:
            if not snaps or snap.seq != snaps[-1].seq:
                snaps.append(snap)
        time.sleep(0.002)
    source.close()
    return source.geometry, snaps


def _heavy(snap: Snapshot, rng: np.random.Generator) -> Snapshot:
    cameras = []
    for frame in snap.cameras:
        est = frame.estimate
        pick = rng.integers(0, len(est.points), N_POINTS)
        points = est.points[pick] + rng.normal(0.0, 0.001, (N_POINTS, 3))
        shells = tuple(
            ShellFit(
                0.04 + 0.02 * i,
                0.06 + 0.02 * i,
                "circle" if i else "plane",
                est.centroid - 0.004 * i * est.normal,
                est.normal,
                60,
                True,
                i % 2 == 0,
                0.03 + 0.01 * i,
            )
            for i in range(4)
        )
        est = dataclasses.replace(
            est, points=points, filled=points[:300], shells=shells, stage_ms=dict(est.stage_ms)
        )
        context = frame.context[rng.integers(0, len(frame.context), N_POINTS)]
        cameras.append(dataclasses.replace(frame, estimate=est, context=context))
    return dataclasses.replace(snap, cameras=tuple(cameras))


@pytest.mark.slow
def test_view_update_rate_with_two_5000_point_clouds(qtbot) -> None:
    from PyQt6 import QtWidgets

    geometry, snaps = _snapshots(40)
    assert len(snaps) >= 20
    rng = np.random.default_rng(0)
    snaps = [_heavy(s, rng) for s in snaps]
    view = SceneView()
    qtbot.addWidget(view, before_close_func=lambda v: v.close_view())
    view.resize(880, 500)  # the 3D view's size in a 1280x800 window
    view.set_geometry(geometry)
    view.show()
    qtbot.waitExposed(view)
    paints = [0]

    def counted(start: float, end: float) -> None:
        paints[0] += 1

    view.canvas.on_paint.append(counted)
    view.show_snapshot(snaps[0])
    qtbot.waitUntil(lambda: paints[0] > 0)
    actors = view.actor_count()
    app = QtWidgets.QApplication.instance()
    t0 = time.perf_counter()
    update_s = []
    for k in range(N_UPDATES):
        want = paints[0] + 1
        a = time.perf_counter()
        view.show_snapshot(snaps[k % len(snaps)])
        update_s.append(time.perf_counter() - a)
        while paints[0] < want:
            app.processEvents()
    rate = N_UPDATES / (time.perf_counter() - t0)
    print(
        f"\nview: {rate:.1f} updates/s with 2 x {N_POINTS} points and every overlay "
        f"(actor update {1e3 * np.median(update_s):.2f} ms median, 880x500 px)"
    )
    assert view.actor_count() == actors
    assert rate > 10.0
