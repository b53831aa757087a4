"""The live source's supervisor: runs the worker off the GUI and publishes its snapshots.

Who runs what
-------------
* A **worker** (:func:`~.worker.run_worker`) owns every object of the data path and sends one
  packet per camera frame down a pipe.
* By default the worker is a separate **process**, so that it never shares a GIL with the GUI:
  VTK's paint holds the GIL for most of its ~20 ms (a spinning Python thread kept 22 % of its
  speed during a paint), and with the worker on a thread the GUI's own Python work took twice as
  long (plot update 6.1 ms instead of 3 ms, whole window, same load) and the view rate dropped
  (13 instead of 20 fps), while a crash or stall of the worker would take the window with it.
  The real session's control loop needs the same separation. ``in_process=True`` runs the same
  function on a thread (debugging, profiling).
* A **receiver** thread in the GUI process turns packets into immutable
  :class:`~.contract.Snapshot` objects numbered by ``seq`` (it keeps the history rings the plots
  read) and publishes the newest by rebinding one attribute, atomic in CPython. The GUI pulls
  :meth:`LiveSource.latest` on its own timer at display rate and drops a snapshot whose ``seq``
  it has shown: nothing at camera or control rate goes through Qt signals, and the worker never
  waits for the GUI.

Requests go the other way: :meth:`LiveSource.request_config` queues a validated
:class:`~.contract.LiveConfig` with a version number (the worker applies the newest one at the
start of its next frame and reports the version it applied); :meth:`LiveSource.emergency_stop`
sets an event the worker checks while pacing and between frames.

No Qt here: the window shows any :class:`~.contract.SnapshotSource` unchanged.
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing as mp
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from hapticloud.core.errors import ConfigError
from hapticloud.core.perception import SurfaceEstimate
from hapticloud.core.studies.demo import CAMERA_RATE_HZ
from hapticloud.core.validation import read_only_copy
from numpy.typing import NDArray

from .contract import (
    CONTROL_RATE_HZ,
    FRAME_COLUMNS,
    HISTORY_S,
    TICK_COLUMNS,
    CameraFrame,
    History,
    LiveConfig,
    SceneGeometry,
    Snapshot,
    SourceState,
)
from .scenes import SimSettings, scene_geometry
from .worker import (
    ContextRequest,
    FramePacket,
    RecordRequest,
    SessionAttach,
    WorkerEnded,
    run_worker,
)

FloatArray = NDArray[np.float64]


class HistoryRing:
    """Fixed-capacity table of float rows; :meth:`ordered` copies it out oldest first."""

    def __init__(self, capacity: int, n_columns: int) -> None:
        self._data = np.full((capacity, n_columns), np.nan)
        self._next = 0
        self._full = False

    def extend(self, rows: FloatArray) -> None:
        for row in np.atleast_2d(rows):
            self._data[self._next] = row
            self._next += 1
            if self._next == len(self._data):
                self._next = 0
                self._full = True

    def ordered(self) -> FloatArray:
        if self._full:
            out = np.concatenate((self._data[self._next :], self._data[: self._next]))
        else:
            out = self._data[: self._next].copy()
        out.setflags(write=False)
        return out


_NO_CONTEXT = np.empty((0, 3), dtype=np.float32)
_NO_CONTEXT.setflags(write=False)


@dataclass
class _Receiver:
    """State the receiver thread keeps to compose snapshots (touched by that thread only)."""

    n_cameras: int
    frames: HistoryRing = field(init=False)
    ticks: HistoryRing = field(init=False)
    newest: dict[int, CameraFrame] = field(default_factory=dict)
    arrivals: dict[int, deque[float]] = field(default_factory=dict)
    clock: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=61))
    config: LiveConfig | None = None

    def __post_init__(self) -> None:
        rows = int(HISTORY_S * CAMERA_RATE_HZ) * self.n_cameras + 1
        self.frames = HistoryRing(rows, len(FRAME_COLUMNS))
        self.ticks = HistoryRing(int(HISTORY_S * CONTROL_RATE_HZ) + 1, len(TICK_COLUMNS))
        self.arrivals = {i: deque(maxlen=31) for i in range(self.n_cameras)}


class LiveSource:
    """Runs a simulated scene live off the GUI thread and publishes :class:`Snapshot` objects.

    Parameters
    ----------
    settings
        Scene, speed and camera resolution.
    config
        Initial parameters (validated: a built :class:`LiveConfig`).
    in_process
        Run the worker on a thread of this process instead of its own process (debugging; the GUI
        slows it down, see the module docstring).
    session
        A running control process to feed (:class:`SessionAttach`): the HIP then comes from the
        robot's shared state and every estimate goes to the loop's fusion.

    Example
    -------
    >>> src = LiveSource(SimSettings(scene="demo"))
    >>> src.start()
    >>> # ... the GUI polls src.latest() on a timer ...
    >>> src.close()
    """

    def __init__(
        self,
        settings: SimSettings | None = None,
        config: LiveConfig | None = None,
        *,
        in_process: bool = False,
        session: SessionAttach | None = None,
    ) -> None:
        self.settings = SimSettings() if settings is None else settings
        self.session = session
        self._config = LiveConfig() if config is None else config
        if not isinstance(self._config, LiveConfig):
            raise ConfigError(f"config: expected a LiveConfig, got {type(config).__name__}")
        self._geometry = scene_geometry(self.settings)
        self._in_process = in_process
        ctx = mp.get_context("spawn")  # never fork a process that runs Qt threads
        self._ctx = ctx
        self._stop = ctx.Event()
        self._requests = ctx.Queue()
        self._version = 0
        self._latest: Snapshot | None = None
        self._state = SourceState.STARTING
        self._message = ""
        self._worker: Any = None
        self._receiver: threading.Thread | None = None
        self._seq = 0
        self._record_sink: Any = None

    # ----- the window's side -------------------------------------------------------------------
    @property
    def geometry(self) -> SceneGeometry:
        return self._geometry

    @property
    def state(self) -> SourceState:
        return self._state

    @property
    def message(self) -> str:
        return self._message

    @property
    def requested_config(self) -> LiveConfig:
        """The newest configuration asked for (the worker applies it at its next frame)."""
        return self._config

    def start(self) -> None:
        """Start the worker and the receiver (once)."""
        if self._worker is not None:
            raise RuntimeError("LiveSource.start: already started")
        recv_end, send_end = self._ctx.Pipe(duplex=False)
        args = (self.settings, self._config, send_end, self._requests, self._stop, self.session)
        if self._in_process:
            self._worker = threading.Thread(
                target=run_worker, args=args, name="hapticloud-sim-worker", daemon=True
            )
        else:
            self._worker = self._ctx.Process(
                target=run_worker,
                args=args,
                kwargs={"own_process": True},
                name="hapticloud-sim-worker",
                daemon=True,
            )
        self._worker.start()
        if not self._in_process:
            send_end.close()  # the child holds it; EOF reaches us when the child exits
        self._receiver = threading.Thread(
            target=self._receive, args=(recv_end,), name="hapticloud-snapshots", daemon=True
        )
        self._receiver.start()

    def attach_session(self, session: SessionAttach) -> None:
        """Feed a control process that came up after :meth:`start` (from the next frame on)."""
        self.session = session
        self._requests.put(session)

    def latest(self) -> Snapshot | None:
        """The newest snapshot (``None`` before the first frame); never blocks."""
        return self._latest

    def record_to(self, sink: Any, record: Any = None) -> None:
        """Record every frame shown from the next one on: the worker cuts it
        (:func:`~hapticloud.hardware.recording.recorder.cut_frame`, ``record`` or the default
        :class:`~hapticloud.core.recording.RecordConfig`) into the display's packet and the
        receiver hands it to ``sink.put_cut(capture time, cut)``; ``None`` stops."""
        from hapticloud.core.recording import RecordConfig

        self._record_sink = sink
        self._requests.put(RecordRequest(None if sink is None else record or RecordConfig()))

    def want_context(self, on: bool) -> None:
        """Render and send the cameras' scene clouds (the window's context layer) or not, from
        the next frame on; the last one received stays in the snapshots."""
        self._requests.put(ContextRequest(bool(on)))

    def request_config(self, config: LiveConfig) -> int:
        """Use ``config`` from the next frame on; returns the request's version number.

        ``config`` is a built, hence validated, :class:`LiveConfig`: an invalid value is refused
        where it is typed (:meth:`StageConfig.replace_path`) and never gets this far.
        """
        if not isinstance(config, LiveConfig):
            raise ConfigError(f"config: expected a LiveConfig, got {type(config).__name__}")
        self._version += 1
        self._config = config
        self._requests.put((self._version, config))
        return self._version

    def emergency_stop(self, reason: str = "emergency stop") -> None:
        """Stop the simulation; returns at once (the worker ends within one frame)."""
        if not self._stop.is_set():
            self._message = reason
            self._stop.set()

    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop and wait for the worker (at most ``timeout_s``, then terminate it)."""
        self.emergency_stop(self._message or "closed")
        worker = self._worker
        if worker is not None:
            worker.join(timeout_s)
            if isinstance(worker, mp.process.BaseProcess) and worker.is_alive():
                worker.terminate()
                worker.join(1.0)
        if self._receiver is not None:
            self._receiver.join(timeout_s)
        self._requests.close()
        self._requests.join_thread()

    @property
    def alive(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    # ----- the receiver thread -----------------------------------------------------------------
    def _receive(self, conn: Any) -> None:
        state = _Receiver(len(self._geometry.cameras))
        end: WorkerEnded | None = None
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                break
            if isinstance(msg, WorkerEnded):
                end = msg
                break
            self._state = SourceState.RUNNING
            sink = self._record_sink
            if sink is not None and msg.record is not None:
                sink.put_cut(msg.captured, msg.record)
            self._latest = self._compose(state, msg)
        conn.close()
        if end is None:
            end = WorkerEnded(
                SourceState.STOPPED if self._stop.is_set() else SourceState.FAILED, ""
            )
        if end.state is SourceState.FAILED:
            self._message = end.message or "the worker ended unexpectedly"
        self._state = end.state
        last = self._latest
        if last is not None:
            self._seq += 1
            self._latest = dataclasses.replace(
                last,
                seq=self._seq,
                state=end.state,
                message=self._message or end.message,
                published=time.monotonic(),
            )

    def _compose(self, state: _Receiver, p: FramePacket) -> Snapshot:
        now = time.monotonic()
        est = SurfaceEstimate(**p.estimate)
        stamps = state.arrivals[p.camera]
        stamps.append(now)
        rate = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 2 else math.nan
        previous = state.newest.get(p.camera)
        if p.context is not None:
            context = read_only_copy(p.context, np.float32)
        elif previous is not None:
            context = previous.context  # read-only already: shared, not copied
        else:
            context = _NO_CONTEXT
        state.newest[p.camera] = CameraFrame(
            name=est.camera,
            estimate=est,
            context=context,
            render_ms=p.render_ms,
            rate_hz=rate,
            d_proj_m=p.d_proj_m,
            error_mm=p.error_mm,
            normal_error_deg=p.normal_error_deg,
        )
        state.frames.extend(np.asarray(p.frame_row, dtype=np.float64))
        if len(p.tick_rows):
            state.ticks.extend(p.tick_rows)
        state.clock.append((now, p.t))
        if p.config is not None:
            state.config = p.config
        self._seq += 1
        (w0, s0), (w1, s1) = state.clock[0], state.clock[-1]
        rtf = (s1 - s0) / (w1 - w0) if len(state.clock) > 2 and w1 > w0 else math.nan
        return Snapshot(
            seq=self._seq,
            t=p.t,
            published=now,
            captured=p.captured,
            state=SourceState.RUNNING,
            message="",
            hip=read_only_copy(p.hip),
            robot=p.robot,
            cameras=tuple(state.newest[i] for i in sorted(state.newest)),
            fused=p.fused,
            fused_d_proj_m=p.fused_d_proj_m,
            truth=p.truth,
            body_offsets=tuple(read_only_copy(o) for o in p.body_offsets),
            config=state.config if state.config is not None else self._config,
            config_version=p.config_version,
            real_time_factor=rtf,
            history=History(state.frames.ordered(), state.ticks.ordered()),
        )
