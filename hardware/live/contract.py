"""What a live source gives the window: the contract between hardware/live and the app.

A source (the simulated one, :class:`~.source.LiveSource`, or a recording played back) publishes
immutable :class:`Snapshot` objects numbered by ``seq``; the window pulls the newest on its own
timer (:class:`SnapshotSource`) and asks for new parameters with a :class:`LiveConfig`. Nothing
here runs: these are the types both sides share, so the app imports them without the worker.
"""

from __future__ import annotations

import enum
import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from hapticloud.core.config import StageConfig, nested
from hapticloud.core.control import ControllerConfig
from hapticloud.core.fusion import FusedSurface, FusionConfig
from hapticloud.core.geometry.primitives import Primitive
from hapticloud.core.loop import HapticsConfig
from hapticloud.core.perception import STAGES, PerceptionConfig, SurfaceEstimate
from hapticloud.core.sim import GroundTruth
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Rate at which the fusion is sampled between camera frames (the haptic control rate).
CONTROL_RATE_HZ = 800.0
#: Seconds of history carried in every snapshot for the live plots.
HISTORY_S = 10.0

#: Per-frame history columns (one row per camera frame).
FRAME_COLUMNS = (
    "t",
    "camera",
    "valid",
    "d_proj_mm",
    "true_d_proj_mm",
    "error_mm",
    "normal_error_deg",
    "fused_error_mm",
    *(f"{stage}_ms" for stage in STAGES),
    "total_ms",
)
#: Per-control-tick history columns (CONTROL_RATE_HZ rows per second).
TICK_COLUMNS = ("t", "valid", "d_proj_mm", "target_d_proj_mm")
#: History columns, one row per control snapshot (100 Hz).
CONTROL_COLUMNS = (
    "t",
    "tick_us",
    "tick_us_max",
    "misses",
    "approach_mps",
    "force_n",
    "d_proj_mm",
    "state",
)


@dataclass(frozen=True)
class LiveConfig(StageConfig):
    """Every parameter the live view tunes, under one root so that a preset holds all tables.

    ``perception`` applies to every camera's pipeline; ``fusion`` to the shared fusion (a fusion
    change restarts the fusion's window: :class:`SurfaceFusion` has no in-place reconfiguration)
    and to the control process's fusion; ``haptics`` to the control process's haptic tick and
    ``controller`` to its hierarchical controller (only while the session is not enabled); the
    worker ignores both.
    """

    perception: PerceptionConfig = nested(PerceptionConfig)
    fusion: FusionConfig = nested(FusionConfig)
    haptics: HapticsConfig = nested(HapticsConfig)
    controller: ControllerConfig = nested(ControllerConfig)


class SourceState(enum.Enum):
    """Lifecycle of a source, as the window shows it."""

    STARTING = "starting"
    RUNNING = "running"
    STOPPED = "stopped"
    FAILED = "failed"


# ----- what the window reads ----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class BodyMesh:
    """Display mesh of one simulated body in its rest pose (m); ``faces`` are triangles."""

    name: str
    part: str
    vertices: FloatArray
    faces: NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class CameraInfo:
    """Where a camera is: optical centre and viewing axis in the world frame."""

    name: str
    origin: FloatArray
    axis: FloatArray


@dataclass(frozen=True, slots=True)
class SceneGeometry:
    """What does not change while a source runs: built into actors once by the view.

    ``robot_shapes`` names the kind (``"sphere"``, ``"capsule"``, ``"box"``) of each primitive of
    :attr:`Snapshot.robot`, in order: their number and kinds are fixed for a source.
    """

    name: str
    cameras: tuple[CameraInfo, ...]
    bodies: tuple[BodyMesh, ...]
    r_hip_m: float
    robot_shapes: tuple[str, ...] = ()
    description: str = ""


@dataclass(frozen=True, slots=True)
class CameraFrame:
    """One camera's newest frame as shown: its estimate, its scene cloud and its errors.

    ``context`` is the frame decimated by :data:`~.worker.CONTEXT_STRIDE` (float32, world, m):
    what the crop removed is shown from it. ``error_mm`` / ``normal_error_deg`` compare the
    estimate with the simulator's truth (NaN when invalid or without truth); ``rate_hz`` is the
    camera's measured frame rate (wall clock) and ``render_ms`` what the simulated camera took.
    """

    name: str
    estimate: SurfaceEstimate
    context: NDArray[np.float32]
    render_ms: float
    rate_hz: float
    d_proj_m: float
    error_mm: float
    normal_error_deg: float


@dataclass(frozen=True, slots=True)
class History:
    """The last :data:`HISTORY_S` seconds, oldest first, as read-only arrays.

    ``frames`` has one row per camera frame with :data:`FRAME_COLUMNS` (``camera`` is the index
    into the scene's cameras); ``ticks`` one row per control tick with :data:`TICK_COLUMNS`.
    """

    frames: FloatArray
    ticks: FloatArray

    def frame(self, column: str) -> FloatArray:
        return self.frames[:, FRAME_COLUMNS.index(column)]

    def tick(self, column: str) -> FloatArray:
        return self.ticks[:, TICK_COLUMNS.index(column)]


@dataclass(frozen=True, slots=True)
class Snapshot:
    """Everything the window shows at one instant; immutable, numbered by ``seq``.

    ``t`` is the source's clock (s; simulation time here); ``captured`` and ``published`` are
    :func:`time.monotonic` times (system-wide, comparable across processes) at which the newest
    frame was taken and the snapshot was published: the window measures frame-to-screen latency
    from ``captured``. ``truth`` and ``body_offsets`` exist only in simulation. ``config`` is the
    configuration the pipelines held for this frame (read back from them) and ``config_version``
    the request it answers (0: the initial one).
    """

    seq: int
    t: float
    published: float
    captured: float
    state: SourceState
    message: str
    hip: FloatArray
    robot: tuple[Primitive, ...]
    cameras: tuple[CameraFrame, ...]
    fused: FusedSurface | None
    fused_d_proj_m: float
    truth: GroundTruth | None
    body_offsets: tuple[FloatArray, ...]
    config: LiveConfig
    config_version: int
    real_time_factor: float
    history: History


class SnapshotSource(Protocol):
    """What the window needs from a source (the simulated one now, the session later)."""

    @property
    def geometry(self) -> SceneGeometry: ...

    @property
    def state(self) -> SourceState: ...

    def start(self) -> None: ...

    def latest(self) -> Snapshot | None: ...

    def request_config(self, config: LiveConfig) -> int: ...

    def emergency_stop(self, reason: str) -> None: ...

    def close(self, timeout_s: float = 2.0) -> None: ...


# ----- the control session, as the window shows it ----------------------------------------------


class SessionPhase(enum.Enum):
    """Life cycle of the control process as the app sees it."""

    STARTING = "starting"
    RUNNING = "running"
    FAILED = "failed"
    CLOSED = "closed"


@dataclass(frozen=True, slots=True)
class Alarm:
    """One line of the alarms list: ``t`` is time.monotonic (s), ``kind`` ``"state"``,
    ``"reaction"`` or ``"app"``."""

    t: float
    kind: str
    text: str

    def clock(self) -> str:
        """Wall-clock time of day, ms."""
        wall = self.t + (time.time() - time.monotonic())
        return time.strftime("%H:%M:%S", time.localtime(wall)) + f".{int(1e3 * (wall % 1)):03d}"
