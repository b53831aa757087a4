"""The supervised hardware session: the control process's handle and its telemetry, for a GUI.

The app runs the 800 Hz control process (:class:`~hapticloud.hardware.control.ControlProcess`,
six emulated drives in their own process) beside the perception worker. :class:`Session` is
the handle the GUI process holds; no Qt here.

* :meth:`Session.start` starts the control process on a helper thread (it takes ~1.5 s to come
  up) and returns at once; :attr:`Session.phase` goes STARTING -> RUNNING, or FAILED with the
  reason in :attr:`Session.message` (the app then runs perception alone).
* Once running, :attr:`Session.attach` is what the perception worker needs at spawn (the
  estimates pipe and the robot state block's name).
* :meth:`Session.poll` is called by the window's timer: it drains the snapshots the control
  process sent since the last call (``cp.snapshots()``: a non-blocking pipe read, ~100 per
  second), keeps a history ring for the plots and the alarms (session transitions and watchdog
  reactions, with their time), and returns the newest. Nothing at 800 Hz reaches the GUI: the
  loop publishes every 8th tick.
* Commands (:meth:`enable`, :meth:`disable`, :meth:`reset`, :meth:`emergency_stop`,
  :meth:`configure`) are one small pipe write each; the loop reads them at its next tick.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
from hapticloud.hardware.control import STATE_CODES
from numpy.typing import NDArray

from .contract import CONTROL_COLUMNS, HISTORY_S, Alarm, SessionPhase
from .source import HistoryRing
from .worker import SessionAttach

#: Snapshots per second the control process publishes (800 Hz / 8).
SNAPSHOT_RATE_HZ = 100.0
#: Alarms kept (newest first in the panel).
MAX_ALARMS = 200
#: The scene files of the app's built-in scenes, for the control process.
CONTROL_SCENES = {"demo": "demo"}


def default_dynamics(scene: str) -> Any:
    """The emulated arm pushed by the scene's simulated patient (a rigid arm when the scene has
    none): :class:`~hapticloud.hardware.drives.scene_arm.SceneArmFactory`."""
    from hapticloud.hardware.drives.scene_arm import SceneArmFactory

    return SceneArmFactory(scene)


#: The control process as the app runs it: the drives answer right after the SYNC (no bus timing
#: model: one wake-up per cycle instead of eight, 10 % of a core instead of 28 %) and the loop
#: spins 50 µs before each deadline instead of 200 µs (tick starts stay within ~25 µs p99):
#: together a quarter of a core left to the 3D view (measured: docs/benchmarks.md, GUI).
APP_PROCESS_KWARGS: dict[str, Any] = {"bus_timing": False, "spin_s": 50e-6}


def scene_tables(scene: str) -> dict[str, Any]:
    """The scene's ``haptics`` and ``controller`` tables as its control process uses them: the
    panel's Haptics and Controller tabs start from these, not from the library defaults."""
    from hapticloud.core.scene import load_scene
    from hapticloud.core.scene.assembly import scene_controller_config

    loaded = load_scene(CONTROL_SCENES.get(scene, scene))
    return {"haptics": loaded.config.haptics, "controller": scene_controller_config(loaded)}


def ready_to_enable(snap: Any) -> bool:
    """Whether a control snapshot shows a session that can be enabled now, as ``--enable`` asks:
    READY, the space around the HIP known (a fresh surface, or proven free) and every watchdog
    quiet. Enabled as soon as it was READY, the first command's session could meet its cameras'
    first estimates on the way: the frame watchdog then held the surface (HOLD_SURFACE) within
    0.3 s of enabling."""
    return snap.state == "ready" and snap.space == "known" and snap.reaction == "NONE"


class Session:
    """The control process of a scene, run and watched from the GUI process.

    Parameters
    ----------
    scene
        The app's scene name (``"demo"``) or a scene file for the control process.
    dynamics
        The emulated arm's dynamics factory; ``"auto"``: :func:`default_dynamics`.
    emulator
        Where the six emulated drives run: ``"stepped"`` (default: in the control tick, on one
        simulation clock with the loop, :class:`~hapticloud.hardware.control.child.SimClock`)
        or ``"process"`` (their own process on wall time, like real drives).
    enable_when_ready
        Enable once, the first time the session reports READY with its surface known and its
        watchdogs quiet (:func:`ready_to_enable`; ``hapticloud app --enable``: the user asked
        for torque on the command line).
    process_kwargs
        More :class:`ControlProcess` arguments; by default :data:`APP_PROCESS_KWARGS`.
    """

    def __init__(
        self,
        scene: str = "demo",
        *,
        dynamics: Any = "auto",
        emulator: str = "stepped",
        enable_when_ready: bool = False,
        **process_kwargs: Any,
    ) -> None:
        self.scene = CONTROL_SCENES.get(scene, scene)
        self._dynamics = default_dynamics(self.scene) if dynamics == "auto" else dynamics
        self._emulator = emulator
        # Simulated drives stepped in the tick share one simulation clock with the loop: on a
        # machine that cannot keep up the simulation slows down (shown) rather than faulting.
        sim = {"sim_clock": True} if emulator == "stepped" else {}
        self._kwargs = {**APP_PROCESS_KWARGS, **sim, **process_kwargs}
        self._enable_when_ready = enable_when_ready
        self._cp: Any = None
        self._phase = SessionPhase.STARTING
        self._message = ""
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._closing = False
        self._pending_estop: str | None = None
        self.info: dict[str, Any] | None = None
        self.latest: Any = None
        self.alarms: deque[Alarm] = deque(maxlen=MAX_ALARMS)
        self.received = 0
        self.lost = 0  # gaps in the snapshots' seq (sent but not seen: none expected)
        self.result: dict[str, Any] | None = None
        self._ring = HistoryRing(int(HISTORY_S * SNAPSHOT_RATE_HZ) + 1, len(CONTROL_COLUMNS))
        #: Called with every batch of drained snapshots (the app's recorder; GUI thread).
        self.listeners: list[Callable[[list[Any]], None]] = []

    # ----- life cycle ---------------------------------------------------------------------------
    def start(self) -> None:
        """Start the control process on a helper thread; returns at once."""
        if self._thread is not None:
            raise RuntimeError("Session.start: already started")
        self._thread = threading.Thread(target=self._start, name="hapticloud-session", daemon=True)
        self._thread.start()

    def start_blocking(self, timeout_s: float = 60.0) -> SessionPhase:
        """Start and wait until running or failed (the bench and tests)."""
        self.start()
        assert self._thread is not None
        self._thread.join(timeout_s)
        return self._phase

    def _start(self) -> None:
        try:
            from hapticloud.hardware.control import ControlProcess

            cp = ControlProcess(
                self.scene, emulator=self._emulator, dynamics=self._dynamics, **self._kwargs
            )
            info = cp.start()
        except Exception as err:  # shown in the panel; perception goes on alone
            text = str(err).strip().splitlines()
            self._message = f"session could not start: {text[-1] if text else type(err).__name__}"
            self._phase = SessionPhase.FAILED
            self.alarms.appendleft(Alarm(time.monotonic(), "app", self._message))
            return
        with self._lock:
            self._cp, self.info = cp, info
            if self._closing:
                return  # close() stops it
            self._phase = SessionPhase.RUNNING
            self._message = ""
            if self._pending_estop is not None:
                cp.emergency_stop(self._pending_estop)
        self.alarms.appendleft(
            Alarm(time.monotonic(), "app", f"control process {cp.pid} started: {_describe(info)}")
        )

    @property
    def phase(self) -> SessionPhase:
        return self._phase

    @property
    def message(self) -> str:
        return self._message

    @property
    def running(self) -> bool:
        return self._phase is SessionPhase.RUNNING

    @property
    def process(self) -> Any:
        """The :class:`ControlProcess` (``None`` until running)."""
        return self._cp if self.running else None

    @property
    def attach(self) -> SessionAttach | None:
        """What the perception worker needs at spawn (``None`` unless running)."""
        cp = self.process
        if cp is None:
            return None
        try:
            return SessionAttach(cp.estimate_connection, cp.state_block_name)
        except RuntimeError:
            return None

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the control process (torque off, drives disabled) and join it (idempotent)."""
        with self._lock:
            self._closing = True
            cp, self._cp = self._cp, None
        if self._thread is not None and self._thread.is_alive():
            self._thread.join(timeout_s)
            with self._lock:
                cp, self._cp = cp or self._cp, None
        if cp is not None:
            try:
                self.result = cp.stop(timeout_s)
            except Exception:
                pass
        if self._phase is not SessionPhase.FAILED:
            self._phase = SessionPhase.CLOSED

    # ----- telemetry ----------------------------------------------------------------------------
    def poll(self) -> Any:
        """Drain the snapshots received since the last call; the newest new one, or ``None``."""
        cp = self.process
        if cp is None:
            return None
        snaps = cp.snapshots()
        if not snaps:
            if not cp.alive and self._phase is SessionPhase.RUNNING:
                why = cp.error.strip().splitlines()[-1] if cp.error else "it exited"
                self._message = f"control process ended: {why}"
                self._phase = SessionPhase.FAILED
                self.alarms.appendleft(Alarm(time.monotonic(), "app", self._message))
            return None
        for listener in self.listeners:
            listener(snaps)
        if self._enable_when_ready and ready_to_enable(snaps[-1]):
            self._enable_when_ready = False
            self.enable()
        rows = np.empty((len(snaps), len(CONTROL_COLUMNS)))
        for k, s in enumerate(snaps):
            if self.latest is not None and s.seq > self.latest.seq + 1:
                self.lost += s.seq - self.latest.seq - 1
            self.latest = s
            force = math.sqrt(sum(f * f for f in s.force_n))
            d_mm = 1e3 * s.d_proj_m if math.isfinite(s.d_proj_m) else math.nan
            rows[k] = (
                s.t,
                s.tick_us,
                s.tick_us_max,
                s.misses,
                s.approach_mps,
                force,
                d_mm,
                STATE_CODES.get(s.state, -1),
            )
            for t, kind, text in s.events:
                self.alarms.appendleft(Alarm(t, kind, text))
        self.received += len(snaps)
        self._ring.extend(rows)
        return self.latest

    def history(self) -> NDArray[np.float64]:
        """The last :data:`HISTORY_S` s of snapshots, oldest first (:data:`CONTROL_COLUMNS`)."""
        return self._ring.ordered()

    # ----- commands -----------------------------------------------------------------------------
    def _command(self, name: str, *args: Any) -> bool:
        cp = self.process
        if cp is None:
            return False
        try:
            getattr(cp, name)(*args)
        except (OSError, RuntimeError, BrokenPipeError):
            return False
        return True

    def enable(self) -> bool:
        return self._command("enable", "enable (app)")

    def disable(self) -> bool:
        return self._command("disable")

    def reset(self) -> bool:
        return self._command("reset")

    def emergency_stop(self, reason: str = "emergency stop (app)") -> bool:
        """E-stop the drives; while the process is still starting, as soon as it runs."""
        with self._lock:
            if self._phase is SessionPhase.STARTING:
                self._pending_estop = reason
                return True
        return self._command("emergency_stop", reason)

    def configure(self, *, haptics: Any = None, fusion: Any = None, controller: Any = None) -> bool:
        """Send new haptics, fusion and/or controller parameters to the loop (False: not sent;
        a controller change while enabled is refused by the loop, shown in the alarms)."""
        cp = self.process
        if cp is None:
            return False
        try:
            cp.configure(haptics=haptics, fusion=fusion, controller=controller)
        except (OSError, RuntimeError, ValueError, TypeError) as err:
            self.alarms.appendleft(Alarm(time.monotonic(), "app", f"configure refused: {err}"))
            return False
        return True


def _describe(info: dict[str, Any]) -> str:
    fifo = "SCHED_FIFO" if info.get("sched_fifo") else "no SCHED_FIFO"
    return f"{info.get('emulator', '?')} emulator, {info.get('bus', '?')}, {fifo}"
