"""The window supervising a session: the control process (800 Hz, six emulated drives in their own
process) beside the perception worker. Enable, e-stop by key, the force arrow, the Haptics table."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hapticloud.app.main_window import MainWindow
from hapticloud.hardware.live.contract import SessionPhase
from hapticloud.hardware.live.scenes import SimSettings
from hapticloud.hardware.live.session import Session
from hapticloud.hardware.live.source import LiveSource
from PyQt6 import QtCore

FAST = SimSettings(decimation=2)
TIMEOUT_MS = 20_000


@pytest.fixture(scope="module")
def supervised(qapp, request):
    from pytestqt.qtbot import QtBot

    qtbot = QtBot(request)
    window = MainWindow(
        lambda cfg, session=None: LiveSource(FAST, cfg, session=session),
        title="demo",
        make_session=lambda: Session("demo"),
    )
    window.resize(1280, 800)
    window.show()
    qtbot.waitExposed(window)
    qtbot.waitUntil(lambda: window.session_panel.state_text() == "ready", timeout=TIMEOUT_MS)
    yield window, qtbot
    window.shutdown()
    window.close()
    assert window.session.phase is SessionPhase.CLOSED
    assert window.session.result is not None  # stopped cleanly: the loop returned its log


def _states(window: MainWindow) -> list[str]:
    return [a.text.split(":")[0] for a in window.session.alarms if a.kind == "state"]


def test_enable_takes_the_session_from_ready_to_enabled(supervised) -> None:
    window, qtbot = supervised
    panel = window.session_panel
    assert panel.enable_button.isEnabled()
    assert window.status.labels["session"].text().strip() == "READY"
    qtbot.mouseClick(panel.enable_button, QtCore.Qt.MouseButton.LeftButton)
    # "enabled" in a later snapshot's events (the watchdogs may fault it again on a loaded
    # machine: the transition itself is what the button does).
    qtbot.waitUntil(lambda: "enabled" in _states(window), timeout=5000)
    # The panel lists alarms on its own refresh timer, at most REFRESH_S after they arrive.
    qtbot.waitUntil(lambda: panel.alarms.topLevelItemCount() > 0, timeout=2000)
    snap = window.session.latest
    assert snap.tick > 0 and len(window.session.history())


def test_force_arrow_moves_without_adding_actors(supervised) -> None:
    window, _ = supervised
    view = window.view
    actors = view.actor_count()
    arrow = view.actor("force")
    fake = SimpleNamespace(force_n=(0.0, 0.0, 10.0), hip_m=(0.3, 0.05, 0.98))
    view.show_control(fake)
    assert arrow.GetVisibility() and view.force_n == pytest.approx(10.0)
    r_hip = window.source.geometry.r_hip_m
    # It starts on the HIP sphere's surface, on the force's side (outside the sphere).
    assert arrow.GetUserMatrix().GetElement(2, 3) == pytest.approx(0.98 + r_hip)
    # 10 N draw 50 mm along the force, as thick as a 60 mm arrow across it.
    user = arrow.GetUserMatrix()
    matrix = np.array([[user.GetElement(i, j) for j in range(3)] for i in range(3)])
    assert np.linalg.norm(matrix, axis=0) == pytest.approx([0.05, 0.06, 0.06])
    first = np.array(arrow.GetUserMatrix().GetElement(2, 3))
    view.show_control(SimpleNamespace(force_n=(5.0, 0.0, 0.0), hip_m=(0.3, 0.05, 1.1)))
    assert arrow.GetUserMatrix().GetElement(2, 3) == pytest.approx(1.1) != first
    assert arrow.GetUserMatrix().GetElement(0, 3) == pytest.approx(0.3 + r_hip)
    assert view.actor_count() == actors
    view.show_control(SimpleNamespace(force_n=(0.0, 0.0, 0.0), hip_m=(0.3, 0.05, 1.1)))
    assert not arrow.GetVisibility()
    assert view.actor_count() == actors


def test_haptics_table_is_in_the_panel(supervised) -> None:
    window, qtbot = supervised
    tabs = [window.panel.tabs.tabText(i) for i in range(window.panel.tabs.count())]
    assert "Haptics" in tabs
    editor = window.panel.editor("haptics.clearance_m")
    assert editor is not None
    # A running session takes haptics and controller changes: both tables become editable.
    qtbot.waitUntil(
        lambda: (
            not window.panel.table_read_only("haptics")
            and not window.panel.table_read_only("controller")
        ),
        timeout=30_000,
    )
    assert window.session.running
    assert window.panel.table_note("haptics") == "Applied to the control loop at its next tick."
    assert "not enabled" in window.panel.table_note("controller")


def test_escape_emergency_stops_the_session(supervised) -> None:
    window, qtbot = supervised
    qtbot.keyClick(window.panel, QtCore.Qt.Key.Key_Escape)
    assert window.stopped
    qtbot.waitUntil(
        lambda: (
            window.session.latest is not None and window.session.latest.state == "emergency_stop"
        ),
        timeout=5000,
    )
    qtbot.waitUntil(lambda: window.session_panel.state_text() == "emergency_stop", timeout=2000)
    assert window.session_panel.reset_button.isEnabled()


def test_the_control_tabs_start_from_the_scene_tables():
    from hapticloud.core.scene import load_scene
    from hapticloud.hardware.live.session import scene_tables

    tables = scene_tables("demo")
    scene = load_scene("demo")
    assert tables["haptics"] == scene.config.haptics
    # As the closed loop builds it: fixed walls keep the HIP sphere out.
    assert tables["controller"].walls.margin_m == scene.config.robot.hip_radius_m
