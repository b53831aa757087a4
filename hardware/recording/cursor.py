"""Playing a recording: what every channel showed at a cursor time, decoded off the GUI thread.

* :func:`read_layout` reads, at open, what does not change: the cameras (name, pose from their
  first capture), the HIP's radius, the kinds of the robot's exclusion shapes and the recorded
  parameters. It reads only the first chunks that hold a capture: the rest of the file stays
  unread (a 10-minute recording opens in a fraction of a second: docs/benchmarks.md).
* :class:`CursorReader` decodes the newest message of each channel at or before a time ``t``
  (:meth:`CursorReader.at`): each camera's newest depth frame with its capture and its recorded
  estimate, the crop of that frame (what perception read), the newest control state, and the
  fused surface (recorded, or re-computed from the recorded estimates where the recording has
  only its validity). Chunks are decompressed once and kept (a few, least recently used), so
  playing forward decompresses each chunk once.
* :class:`RecordingPlayer` holds the cursor: a thread decodes the newest requested time (seek,
  step, or the wall clock times the speed while playing) and publishes an immutable
  :class:`CursorView` by rebinding one attribute; a second thread runs the
  :class:`~.timeline.TimelineScan`. A re-run with other parameters runs in a process of its own
  (:mod:`.rerun`). No Qt: the app's widgets poll :attr:`RecordingPlayer.view`.
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from hapticloud.core.errors import ConfigError, RecordingError
from hapticloud.core.fusion import FusedSurface, FusionConfig, SurfaceFusion
from hapticloud.core.geometry.primitives import Box, Capsule, Primitive, Sphere
from hapticloud.core.perception import PerceptionConfig, SurfaceEstimate
from hapticloud.core.perception.crop import crop_depth_frame
from hapticloud.core.recording import CapturedFrame, primitive_from_dict, replay_configs
from numpy.typing import NDArray

from . import format as fmt
from .reader import ChunkSpan, Recording, record_message
from .timeline import TimelineData, TimelineScan, empty_timeline

FloatArray = NDArray[np.float64]

#: Every n-th pixel of a frame's stored rectangle is kept as the camera's scene cloud.
CONTEXT_STRIDE = 4
#: Chunks kept decompressed (a chunk holds ~0.5 s of a session).
CACHE_CHUNKS = 8
#: How far back the cursor looks for a channel's newest message before it asks the file for
#: older ones (s): a camera's frame at 30 Hz is never older than this while it runs.
WINDOWS_S = (0.25, 2.0, 15.0, math.inf)
#: Frames per second the player decodes while playing.
PLAY_RATE_HZ = 30.0
SPEEDS = (0.1, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
#: Robot shapes the view has slots for (the exoskeleton's links, the ball, the handle).
ROBOT_SLOTS = 24


@dataclass(frozen=True)
class CameraLayout:
    """A recorded camera: its name and, from its first capture, optical centre and axis."""

    name: str
    origin: FloatArray
    axis: FloatArray


@dataclass(frozen=True)
class RecordingLayout:
    """What does not change over a recording (see :func:`read_layout`)."""

    name: str
    cameras: tuple[CameraLayout, ...]
    r_hip_m: float
    shapes: tuple[str, ...]
    perception: PerceptionConfig
    fusion: FusionConfig
    description: str = ""
    note: str = ""


@dataclass(frozen=True)
class CameraAt:
    """One camera at the cursor: its newest frame (``None`` before its first), the crop of that
    frame (float32 world points: what perception read), every ``CONTEXT_STRIDE``-th pixel of its
    stored rectangle, and the estimate recorded for that frame (``None`` if none)."""

    name: str
    log_time_s: float
    frame: CapturedFrame | None
    cropped: NDArray[np.float32]
    context: NDArray[np.float32]
    estimate: SurfaceEstimate | None


@dataclass(frozen=True)
class CursorView:
    """Everything at the cursor ``t`` (the recording's clock), numbered by ``seq``.

    ``requested`` is the :func:`time.monotonic` time of the seek (or play step) it answers and
    ``decoded`` when it was ready: ``decoded - requested`` is the seek's decode latency.
    ``fused_source`` says where ``fused`` comes from: ``"recorded"`` (the control state),
    ``"estimates"`` (re-computed from the recorded estimates) or ``""`` (none).
    """

    seq: int
    t: float
    requested: float
    decoded: float
    cameras: tuple[CameraAt, ...]
    hip: FloatArray | None
    robot: tuple[Primitive, ...]
    control: dict[str, Any] | None
    fused: FusedSurface | None
    fused_d_proj_m: float
    fused_source: str = ""
    error: str = ""

    @property
    def decode_ms(self) -> float:
        return 1e3 * (self.decoded - self.requested)


# ----- layout -------------------------------------------------------------------------------------
def _kind(prim: Primitive) -> str:
    return {Sphere: "sphere", Capsule: "capsule", Box: "box"}.get(type(prim), "sphere")


def recorded_configs(rec: Recording) -> tuple[PerceptionConfig, FusionConfig, str]:
    """The recording's perception and fusion parameters, and a note when they could not be
    read (then the defaults)."""
    try:
        perception, fusion = replay_configs(rec.config_toml())
        return perception, fusion, ""
    except ConfigError as err:
        return PerceptionConfig(), FusionConfig(), f"recorded parameters unreadable ({err})"


def read_layout(rec: Recording) -> RecordingLayout:
    """Cameras, HIP radius, robot shapes and parameters of ``rec`` from its first chunks."""
    from hapticloud.core.studies.perception import R_HIP_M

    # By name: a camera keeps its colour whichever camera's frame reached the file first.
    cameras = sorted(rec.cameras)
    wanted = {fmt.capture_topic(c): c for c in cameras}
    first: dict[str, dict[str, Any]] = {}
    r_hip = math.nan
    kinds: list[str] = []
    spans = sorted(rec.chunk_spans(), key=lambda s: s.start_ns)
    looked = 0
    for span in spans:
        need_capture = len(first) < len(cameras) and bool(span.topics & wanted.keys())
        need_surface = math.isnan(r_hip) and fmt.SURFACE_TOPIC in span.topics
        if not (need_capture or need_surface):
            continue
        for topic, _ns, data in rec.chunk_messages(span.key):
            if topic in wanted and wanted[topic] not in first:
                cap = rec.decode(topic, data)
                first[wanted[topic]] = cap
                prims = [_kind(primitive_from_dict(p)) for p in cap.get("exclude", ())]
                if len(prims) > len(kinds):
                    kinds = prims
            elif topic == fmt.SURFACE_TOPIC and math.isnan(r_hip):
                r_hip = _surface_radius(rec.decode(topic, data))
        looked += 1
        if (len(first) == len(cameras) and not math.isnan(r_hip)) or looked >= 8:
            break
    cams = []
    for name in cameras:
        cap = first.get(name)
        if cap is None:
            cams.append(CameraLayout(name, np.zeros(3), np.array([1.0, 0.0, 0.0])))
            continue
        pose = np.asarray(cap["pose_world_camera"], dtype=np.float64).reshape(4, 4)
        cams.append(CameraLayout(name, pose[:3, 3].copy(), pose[:3, 2].copy()))
    perception, fusion, note = recorded_configs(rec)
    info = rec.info
    scene = info.get("scene") or Path(rec.path).stem
    description = (
        f"recording of {info.get('source', '?')} ({scene}), {rec.duration_s:.1f} s, "
        f"{'complete' if rec.finished else 'UNFINISHED'}"
    )
    # Slots for more shapes than the first frames had (a session that drives the robot adds its
    # links: capsules); the view hides the slots a frame does not use.
    kinds += ["capsule"] * max(0, ROBOT_SLOTS - len(kinds))
    return RecordingLayout(
        name=scene,
        cameras=tuple(cams),
        r_hip_m=r_hip if math.isfinite(r_hip) and r_hip > 0 else R_HIP_M,
        shapes=tuple(kinds),
        perception=perception,
        fusion=fusion,
        description=description,
        note=note,
    )


def _surface_radius(update: Any) -> float:
    for entity in getattr(update, "entities", ()):
        if entity.id == "hip" and entity.spheres:
            return float(entity.spheres[0].size.x) / 2.0
    return math.nan


# ----- decoding at a time -------------------------------------------------------------------------
class CursorReader:
    """Decodes :class:`CursorView` s from one :class:`Recording` (one thread uses it)."""

    def __init__(
        self, rec: Recording, layout: RecordingLayout, cache_chunks: int = CACHE_CHUNKS
    ) -> None:
        self.rec = rec
        self.layout = layout
        self._spans: list[ChunkSpan] = sorted(rec.chunk_spans(), key=lambda s: s.start_ns)
        self._starts = [s.start_ns for s in self._spans]
        # Chunks never end before they start; the longest one bounds the look-back below.
        self._longest = max((s.end_ns - s.start_ns for s in self._spans), default=0)
        self._cache: OrderedDict[int, list[tuple[str, int, bytes]]] = OrderedDict()
        self._cache_size = cache_chunks
        self._topics = set(rec.channels)
        self._seq = 0
        self.chunks_read = 0
        self._by_topic: dict[str, tuple[list[ChunkSpan], list[int]]] = {}
        self._indexes: dict[tuple[int, str], tuple[NDArray, NDArray]] = {}
        self._raw: OrderedDict[int, bytes] = OrderedDict()

    # ----- raw windows ----------------------------------------------------------------------------
    def _chunk(self, key: int) -> list[tuple[str, int, bytes]]:
        got = self._cache.get(key)
        if got is not None:
            self._cache.move_to_end(key)
            return got
        got = self.rec.chunk_messages(key)
        self.chunks_read += 1
        self._cache[key] = got
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return got

    def window(self, topics: Iterable[str], lo_ns: int, hi_ns: int) -> list[tuple[str, int, bytes]]:
        """Messages of ``topics`` with ``lo_ns <= log time <= hi_ns``, by log time."""
        wanted = set(topics) & self._topics
        if not wanted:
            return []
        # Chunks starting after hi_ns cannot hold a message at or before it.
        stop = bisect.bisect_right(self._starts, hi_ns)
        first = bisect.bisect_left(self._starts, lo_ns - self._longest)
        out: list[tuple[str, int, bytes]] = []
        for span in self._spans[first:stop]:
            if span.end_ns < lo_ns or not (span.topics & wanted):
                continue
            out.extend(
                m for m in self._chunk(span.key) if m[0] in wanted and lo_ns <= m[1] <= hi_ns
            )
        out.sort(key=lambda m: m[1])
        return out

    def newest(
        self, topics: Sequence[str], t_s: float, exact_s: dict[str, float] | None = None
    ) -> dict[str, tuple[int, bytes]]:
        """The newest message at or before ``t_s`` of each of ``topics``, looking back through
        :data:`WINDOWS_S` until each is found (or the file's start). ``exact_s`` gives, for some
        topics, the log time of that message (from the timeline scan): it is read alone."""
        hi = fmt.to_ns(t_s)
        found: dict[str, tuple[int, bytes]] = {}
        exact = exact_s or {}
        if self.rec.indexed:
            # Each chunk's message index says where a topic's messages are: the newest one is
            # found without parsing a chunk, and read alone, however far back it is.
            for topic in [*exact, *topics]:
                if topic in found or topic not in self._topics:
                    continue
                got = self._newest_indexed(topic, hi)
                if got is not None:
                    found[topic] = got
            return found
        for topic, when in exact.items():
            ns = fmt.to_ns(when)
            for tp, mns, data in self.window([topic], ns - 1000, min(hi, ns + 1000)):
                if tp == topic:
                    found[topic] = (mns, data)
        missing = [t for t in topics if t not in found and t in self._topics]
        start_ns = fmt.to_ns(self.rec.start_s)
        for span in WINDOWS_S:
            if not missing:
                break
            lo = start_ns if math.isinf(span) else max(start_ns, hi - fmt.to_ns(span))
            for tp, mns, data in self.window(missing, lo, hi):
                found[tp] = (mns, data)
            missing = [t for t in missing if t not in found]
            if lo <= start_ns:
                break
        return found

    def at_time(self, topic: str, ns: int) -> tuple[int, bytes] | None:
        """The message of ``topic`` logged at exactly ``ns`` (``None`` if none)."""
        if self.rec.indexed:
            got = self._newest_indexed(topic, ns)
            return got if got is not None and got[0] == ns else None
        same = [(mns, data) for tp, mns, data in self.window([topic], ns, ns) if tp == topic]
        return same[-1] if same else None

    # ----- indexed files ----------------------------------------------------------------------
    def _topic_spans(self, topic: str) -> tuple[list[ChunkSpan], list[int]]:
        """The chunks holding ``topic`` by the log time of their last message, and those ends."""
        got = self._by_topic.get(topic)
        if got is None:
            spans = sorted((s for s in self._spans if topic in s.topics), key=lambda s: s.end_ns)
            got = self._by_topic[topic] = (spans, [s.end_ns for s in spans])
        return got

    def _message_index(self, key: int, topic: str) -> tuple[NDArray, NDArray]:
        cache_key = (key, topic)
        got = self._indexes.get(cache_key)
        if got is None:
            got = self._indexes[cache_key] = self.rec.chunk_topic_index(key, topic)
            if len(self._indexes) > 8192:
                self._indexes.pop(next(iter(self._indexes)))
        return got

    def _records(self, key: int) -> bytes:
        got = self._raw.get(key)
        if got is not None:
            self._raw.move_to_end(key)
            return got
        got = self.rec.chunk_records(key)
        self.chunks_read += 1
        self._raw[key] = got
        while len(self._raw) > self._cache_size:
            self._raw.popitem(last=False)
        return got

    def _newest_indexed(self, topic: str, hi_ns: int) -> tuple[int, bytes] | None:
        """Chunks are visited by their end, newest first: those still open at ``hi_ns`` (they
        may hold a message at or before it), then the ones that ended before it, until one
        ends before the best message found (a chunk of a deterministic run's control states,
        written at its end, can span the whole run: its start says nothing)."""
        spans, ends = self._topic_spans(topic)
        best: tuple[int, int, int] | None = None  # (log time, chunk key, offset)

        def visit(span: ChunkSpan) -> None:
            nonlocal best
            times, offsets = self._message_index(span.key, topic)
            j = int(np.searchsorted(times, hi_ns, side="right")) - 1
            if j >= 0 and (best is None or int(times[j]) > best[0]):
                best = (int(times[j]), span.key, int(offsets[j]))

        k = bisect.bisect_left(ends, hi_ns)
        for span in spans[k:]:
            if span.start_ns <= hi_ns:
                visit(span)
        i = k - 1
        while i >= 0 and (best is None or ends[i] >= best[0]):
            visit(spans[i])
            i -= 1
        if best is None:
            return None
        return record_message(self._records(best[1]), best[2])

    # ----- one view -------------------------------------------------------------------------------
    def at(
        self, t_s: float, timeline: TimelineData | None = None, requested: float | None = None
    ) -> CursorView:
        """What every channel showed at ``t_s`` (see :class:`CursorView`)."""
        requested = time.monotonic() if requested is None else requested
        t_s = min(max(t_s, self.rec.start_s), self.rec.end_s)
        layout = self.layout
        topics: list[str] = []
        exact: dict[str, float] = {}
        for cam in layout.cameras:
            trio = (fmt.depth_topic(cam.name), fmt.capture_topic(cam.name))
            lane = timeline.camera(cam.name) if timeline is not None else None
            if lane is not None and timeline is not None and timeline.covers(t_s):
                i = lane.newest_at(t_s)
                if i >= 0:
                    for topic in (*trio, fmt.estimate_topic(cam.name)):
                        exact[topic] = float(lane.t[i])
                    continue
            topics += trio
        found = self.newest(topics, t_s, exact)
        cameras = [self._camera(cam.name, found) for cam in layout.cameras]
        control = self._control(t_s)
        newest = max(
            (c for c in cameras if c.frame is not None),
            key=lambda c: c.log_time_s,
            default=None,
        )
        hip: FloatArray | None = None
        if control is not None and control.get("hip") is not None:
            hip = np.asarray(control["hip"], dtype=np.float64)
            if not (hip.shape == (3,) and np.isfinite(hip).all()):
                hip = None
        if hip is None and newest is not None and newest.frame is not None:
            hip = np.asarray(newest.frame.hip, dtype=np.float64)
        robot = newest.frame.exclude if newest is not None and newest.frame is not None else ()
        fused, source = self._fused(t_s, control, timeline)
        d_proj = math.nan
        if control is not None and control.get("d_proj_m") is not None:
            d_proj = float(control["d_proj_m"])
        elif fused is not None and fused.valid and hip is not None:
            from hapticloud.core.haptics import d_proj as _d_proj

            d_proj = _d_proj(fused.centroid, fused.normal, hip, layout.r_hip_m)
        self._seq += 1
        return CursorView(
            seq=self._seq,
            t=t_s,
            requested=requested,
            decoded=time.monotonic(),
            cameras=tuple(cameras),
            hip=hip,
            robot=tuple(robot),
            control=control,
            fused=fused,
            fused_d_proj_m=d_proj,
            fused_source=source,
        )

    def _camera(self, name: str, found: dict[str, tuple[int, bytes]]) -> CameraAt:
        empty = np.empty((0, 3), dtype=np.float32)
        depth = found.get(fmt.depth_topic(name))
        capture = found.get(fmt.capture_topic(name))
        if depth is None or capture is None:
            return CameraAt(name, math.nan, None, empty, empty, None)
        if depth[0] != capture[0]:
            # The newest of the two is not a pair (a torn end): take the older one's pair.
            ns = min(depth[0], capture[0])
            depth = self.at_time(fmt.depth_topic(name), ns)
            capture = self.at_time(fmt.capture_topic(name), ns)
            if depth is None or capture is None:
                return CameraAt(name, math.nan, None, empty, empty, None)
        ns = capture[0]
        log_t = ns / 1e9
        cap_msg = self.rec.decode(fmt.capture_topic(name), capture[1])
        depth_msg = self.rec.decode(fmt.depth_topic(name), depth[1])
        frame = self.rec.captured_frame(cap_msg, depth_msg, log_t)
        crop = crop_depth_frame(frame.frame, frame.hip, frame.exclude, self.layout.perception.crop)
        cropped = np.asarray(crop.points, dtype=np.float32)
        r0, r1, c0, c1 = frame.roi
        stride = slice(None, None, CONTEXT_STRIDE)
        sub = frame.frame.depth_m[r0:r1, c0:c1]
        context = empty
        if sub.size:
            rows = slice(r0, r1, CONTEXT_STRIDE)
            cols = slice(c0, c1, CONTEXT_STRIDE)
            context = frame.frame.points_world(rows, cols).astype(np.float32)
        del stride
        est = None
        est_msg = found.get(fmt.estimate_topic(name))
        if est_msg is None or est_msg[0] != ns:
            est_msg = self.at_time(fmt.estimate_topic(name), ns)
        if est_msg is not None:
            est = self._estimate(self.rec.decode(fmt.estimate_topic(name), est_msg[1]), cropped)
        return CameraAt(name, log_t, frame, cropped, context, est)

    def _estimate(self, wire: dict[str, Any], points: NDArray[np.float32]) -> SurfaceEstimate:
        from ..control.messages import estimate_from_dict

        try:
            est = estimate_from_dict(wire)
        except (KeyError, TypeError, ValueError) as err:
            raise RecordingError(f"{self.rec.path}: bad estimate ({err})") from None
        import dataclasses

        return dataclasses.replace(est, points=points if len(points) else None)

    def _control(self, t_s: float) -> dict[str, Any] | None:
        if fmt.CONTROL_TOPIC not in self._topics:
            return None
        found = self.newest([fmt.CONTROL_TOPIC], t_s)
        got = found.get(fmt.CONTROL_TOPIC)
        if got is None:
            return None
        data = self.rec.decode(fmt.CONTROL_TOPIC, got[1])
        return dict(data, log_time_s=got[0] / 1e9) if isinstance(data, dict) else None

    def _fused(
        self, t_s: float, control: dict[str, Any] | None, timeline: TimelineData | None
    ) -> tuple[FusedSurface | None, str]:
        if control is not None and control.get("fused_centroid") is not None:
            c = np.asarray(control["fused_centroid"], dtype=np.float64)
            n = np.asarray(control.get("fused_normal") or (0.0, 0.0, 1.0), dtype=np.float64)
            if c.shape == (3,) and n.shape == (3,) and np.isfinite(c).all():
                return _fused_surface(t_s, c, n, bool(control.get("fused_valid"))), "recorded"
        ests = self._recent_estimates(t_s, timeline)
        if not ests:
            return None, ""
        fusion = SurfaceFusion(self.layout.fusion)
        for est in ests:
            fusion.add(est)
        return fusion.sample(t_s), "estimates"

    def _recent_estimates(self, t_s: float, timeline: TimelineData | None) -> list[SurfaceEstimate]:
        """The recorded estimates of the fusion's window before ``t_s``, on the log clock."""
        span = self.layout.fusion.window_s + 0.05
        out: list[SurfaceEstimate] = []
        if timeline is not None and timeline.covers(t_s):
            for lane in timeline.cameras:
                lo = bisect.bisect_left(lane.t, t_s - span)  # type: ignore[arg-type]
                hi = lane.newest_at(t_s) + 1
                for i in range(lo, hi):
                    out.append(
                        SurfaceEstimate(
                            float(lane.t[i]),
                            lane.name,
                            lane.centroid[i],
                            lane.normal[i],
                            bool(lane.valid[i]),
                        )
                    )
        else:
            from ..control.messages import estimate_from_dict

            topics = [fmt.estimate_topic(c.name) for c in self.layout.cameras]
            import dataclasses

            for tp, ns, data in self.window(topics, fmt.to_ns(t_s - span), fmt.to_ns(t_s)):
                try:
                    est = estimate_from_dict(self.rec.decode(tp, data))
                except (KeyError, TypeError, ValueError):
                    continue
                out.append(dataclasses.replace(est, t=ns / 1e9))
        out.sort(key=lambda e: e.t)
        return out


def _fused_surface(t: float, centroid: FloatArray, normal: FloatArray, valid: bool) -> FusedSurface:
    norm = float(np.linalg.norm(normal)) or 1.0
    n = normal / norm
    return FusedSurface(
        t=t,
        centroid=centroid,
        normal=n,
        valid=valid,
        velocity=np.zeros(3),
        target_centroid=centroid,
        target_normal=n,
        age_s=math.nan,
        stale=False,
        reason="" if valid else "recorded invalid",
        n_samples=0,
        degree=0,
        cameras=(),
        seq=0,
    )


# ----- the player ---------------------------------------------------------------------------------
@dataclass
class _Transport:
    """The cursor's request state (guarded by the player's condition)."""

    target: float
    playing: bool = False
    speed: float = 1.0
    anchor_t: float = 0.0
    anchor_wall: float = 0.0
    requested: float = 0.0
    generation: int = 0
    closed: bool = False
    shown_generation: int = -1
    errors: list[str] = field(default_factory=list)


class RecordingPlayer:
    """A recording opened for playing: cursor, transport and timeline (see the module docstring).

    ``Recording.open`` errors (:class:`RecordingError`, one line) are raised here, before any
    thread starts. Call :meth:`start` to decode the first view and scan the timeline,
    :meth:`close` at the end.
    """

    def __init__(self, path: str | Path, *, scan: bool = True) -> None:
        self.path = Path(path)
        self.rec = Recording.open(path)
        try:
            self.layout = read_layout(self.rec)
            self._reader = CursorReader(self.rec, self.layout)
        except BaseException:
            self.rec.close()
            raise
        self.start_s, self.end_s = self.rec.start_s, self.rec.end_s
        #: The newest decoded view (``None`` until the first); rebound, never mutated.
        self.view: CursorView | None = None
        #: What the timeline scan has read (rebound as it goes).
        self.timeline: TimelineData = empty_timeline(
            self.start_s, self.end_s, [c.name for c in self.layout.cameras]
        )
        self.error = ""
        self._scan_enabled = scan
        self._cond = threading.Condition()
        self._tr = _Transport(target=self.start_s)
        self._threads: list[threading.Thread] = []
        self.rerun: Any = None

    # ----- life cycle -----------------------------------------------------------------------------
    def start(self) -> None:
        """Start the cursor thread (it decodes the start at once) and the timeline scan."""
        if self._threads:
            raise RuntimeError("RecordingPlayer.start: already started")
        if self._tr.generation == 0:  # no seek asked for yet: show the start
            self.seek(self.start_s)
        with self._cond:  # a seek asked for before the start counts from now
            self._tr.requested = time.monotonic()
        cursor = threading.Thread(target=self._cursor_loop, name="hapticloud-cursor", daemon=True)
        self._threads.append(cursor)
        if self._scan_enabled:
            scan = threading.Thread(target=self._scan, name="hapticloud-scan", daemon=True)
            self._threads.append(scan)
        for th in self._threads:
            th.start()

    def close(self, timeout_s: float = 2.0) -> None:
        with self._cond:
            self._tr.closed = True
            self._cond.notify_all()
        for th in self._threads:
            th.join(timeout_s)
        if self.rerun is not None:
            self.rerun.cancel()
        self.rec.close()

    @property
    def closed(self) -> bool:
        return self._tr.closed

    # ----- transport (any thread) -----------------------------------------------------------------
    @property
    def position(self) -> float:
        """The cursor now (s, recording clock): moving with the wall clock while playing."""
        tr = self._tr
        if tr.playing:
            t = tr.anchor_t + (time.monotonic() - tr.anchor_wall) * tr.speed
            return min(t, self.end_s)
        return tr.target

    @property
    def playing(self) -> bool:
        return self._tr.playing

    @property
    def speed(self) -> float:
        return self._tr.speed

    def _request(self, t: float, *, playing: bool | None = None) -> None:
        """(with the condition held) Move the target to ``t`` and wake the cursor."""
        tr = self._tr
        now = time.monotonic()
        tr.target = min(max(float(t), self.start_s), self.end_s)
        tr.anchor_t, tr.anchor_wall = tr.target, now
        tr.requested = now
        if playing is not None:
            tr.playing = playing
        tr.generation += 1
        self._cond.notify_all()

    def seek(self, t: float) -> None:
        """Show time ``t`` (clamped to the recording); playing goes on from there."""
        if not math.isfinite(t):
            return
        with self._cond:
            self._request(t)

    def step(self, dt: float) -> None:
        """Move the cursor by ``dt`` seconds (pauses playing: a step is a precise move)."""
        with self._cond:
            self._request(self.position + dt, playing=False)

    def play(self) -> None:
        with self._cond:
            start = self.position
            if start >= self.end_s - 1e-9:
                start = self.start_s  # at the end: play again from the start
            self._request(start, playing=True)

    def pause(self) -> None:
        with self._cond:
            self._request(self.position, playing=False)

    def toggle(self) -> bool:
        """Play or pause; returns whether it plays now."""
        if self._tr.playing:
            self.pause()
        else:
            self.play()
        return self._tr.playing

    def set_speed(self, speed: float) -> None:
        if not (math.isfinite(speed) and 0 < speed <= 64):
            raise ConfigError(f"speed = {speed}: must be in (0, 64]")
        with self._cond:
            now = self.position
            self._tr.speed = float(speed)
            self._tr.anchor_t, self._tr.anchor_wall = now, time.monotonic()
            self._cond.notify_all()

    # ----- threads --------------------------------------------------------------------------------
    def _cursor_loop(self) -> None:
        period = 1.0 / PLAY_RATE_HZ
        while True:
            with self._cond:
                tr = self._tr
                while not tr.closed and not tr.playing and tr.generation == tr.shown_generation:
                    self._cond.wait(0.5)
                if tr.closed:
                    return
                generation = tr.generation
                if tr.playing:
                    t = self.position
                    requested = time.monotonic()
                    if t >= self.end_s:
                        t = self.end_s
                        tr.playing = False
                        tr.target = t
                else:
                    t, requested = tr.target, tr.requested
                tr.shown_generation = generation
            began = time.monotonic()
            try:
                self.view = self._reader.at(t, self.timeline, requested)
                self.error = ""
            except (RecordingError, ValueError, KeyError, OSError) as err:
                self.error = str(err).splitlines()[0] if str(err) else type(err).__name__
            if self._tr.playing:
                rest = period - (time.monotonic() - began)
                if rest > 0:
                    with self._cond:
                        if self._tr.generation == generation:
                            self._cond.wait(rest)

    def _scan(self) -> None:
        try:
            rec = Recording.open(self.path)
        except RecordingError as err:
            self.timeline = self._failed_timeline(str(err))
            return
        try:
            scan = TimelineScan(rec, self.layout.r_hip_m)

            def publish(data: TimelineData) -> None:
                self.timeline = data

            scan.run(publish, stop=lambda: self._tr.closed)
        finally:
            rec.close()

    def _failed_timeline(self, error: str) -> TimelineData:
        import dataclasses

        return dataclasses.replace(self.timeline, error=error)

    # ----- re-run --------------------------------------------------------------------------------
    def start_rerun(self, perception: PerceptionConfig, fusion: FusionConfig) -> Any:
        """Re-run perception and fusion on the whole recording with these parameters in a
        process of its own (:class:`~.rerun.ReRun`); replaces (cancels) a running one."""
        from .rerun import ReRun

        if self.rerun is not None:
            self.rerun.cancel()
        self.rerun = ReRun(self.path, perception, fusion, [c.name for c in self.layout.cameras])
        return self.rerun


__all__ = [
    "CONTEXT_STRIDE",
    "PLAY_RATE_HZ",
    "SPEEDS",
    "CameraAt",
    "CameraLayout",
    "CursorReader",
    "CursorView",
    "RecordingLayout",
    "RecordingPlayer",
    "read_layout",
    "recorded_configs",
]
