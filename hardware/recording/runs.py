"""Recording a run: the recorder of a scene's run, and the tick's view as a control-state message.

``hapticloud run SCENE --record FILE`` (the deterministic run) hands the simulator's frame hook a
blocking :class:`~.recorder.RecordSink` (the simulated run has no deadline, so nothing is ever
dropped) and, once the run is over, writes every tick of its record as control states; the
run computes exactly what it computes without recording (the hook only reads). ``run
--hardware --record FILE`` gives the perception process a non-blocking sink and forwards the
control process's snapshots, which the session drains anyway (:mod:`..session.run`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from hapticloud.core.recording import RecordConfig

from .recorder import Recorder, RecordSink, config_tomls

#: Ticks between two control states in the deterministic run (as the control process's snapshots).
#: A deterministic run records every tick of its control loop (the 800 Hz robot state).
CONTROL_EVERY_TICKS = 1


def scene_recorder(
    path: str,
    scene: Any,
    source: str,
    clock: str,
    record: RecordConfig | None = None,
    limit_bytes: int | None = None,
) -> Recorder:
    """A started :class:`Recorder` for a run of ``scene`` (its parameters and TOML as metadata)."""
    import tomli_w

    cfg = scene.config
    recorder = Recorder(
        path,
        {"source": source, "clock": clock, "scene": scene.name},
        config_tomls(cfg.perception, cfg.fusion),
        {"name": scene.name, "path": str(scene.path), "toml": tomli_w.dumps(scene.data)},
        record=record,
        crop=cfg.perception.crop,
        limit_bytes=limit_bytes,
    )
    recorder.wait_ready()
    return recorder


def demo_recorder(path: str, perception: Any, limit_bytes: int | None = None) -> Recorder:
    """A started :class:`Recorder` for ``hapticloud demo`` (no scene file: its parameters only)."""
    from hapticloud.core.fusion import FusionConfig

    recorder = Recorder(
        path,
        {"source": "demo", "clock": "scene", "scene": "demo"},
        config_tomls(perception, FusionConfig()),
        None,
        crop=perception.crop,
        limit_bytes=limit_bytes,
    )
    recorder.wait_ready()
    return recorder


def frame_hook(sink: RecordSink) -> Any:
    """The simulator's ``frame_sink``: each processed frame, on the scene clock."""

    def hook(frame: Any, hip: Any, exclude: Any, estimate: Any) -> None:
        sink.capture(frame.t, frame, hip, exclude, estimate)

    return hook


_SPACE = ("known", "holding", "stopped")


def _vec(a: Any) -> list[float]:
    return [float(x) for x in np.asarray(a).reshape(-1)]


def record_ticks(sink: RecordSink, record: Any, every: int = CONTROL_EVERY_TICKS) -> int:
    """Every ``every``-th tick of a :class:`~hapticloud.core.sim.closed_loop.RunRecord` as a
    control state; returns how many were sent."""
    a = record.arrays
    n = 0
    for k in range(0, record.n_ticks, every):
        fused = bool(a["fused_valid"][k])
        space = int(a["space"][k])
        state = {
            "t": float(a["t"][k]),
            "hip": _vec(a["hip"][k]),
            "q": _vec(a["q"][k]),
            "tau": _vec(a["tau"][k]),
            "d_proj_m": float(a["d_proj"][k]),
            "fused_valid": fused,
            "fused_centroid": _vec(a["fused_centroid"][k]),
            "fused_normal": _vec(a["fused_normal"][k]),
            "true_margin_m": float(a["margin"][k]),
            "state": "simulated",
            "space": _SPACE[space] if 0 <= space < len(_SPACE) else str(space),
        }
        sink.control_state(state["t"], state, record.hip_radius_m)
        n += 1
    return n


def snapshot_state(snap: Any) -> dict[str, Any]:
    """A :class:`~hapticloud.hardware.control.messages.ControlSnapshot` as a control state."""
    return {
        "t": float(snap.t),
        "hip": list(snap.hip_m),
        "q": list(snap.q),
        "tau": list(snap.tau_sent),
        "d_proj_m": float(snap.d_proj_m) if math.isfinite(snap.d_proj_m) else None,
        "fused_valid": bool(snap.fused_valid),
        "state": snap.state,
        "reaction": snap.reaction,
        "space": snap.space,
        "space_reason": snap.space_reason,
        "tick_us": float(snap.tick_us),
        "misses": int(snap.misses),
    }


def record_snapshots(sink: RecordSink, snaps: list[Any], hip_radius_m: float) -> None:
    """Control states and events of drained snapshots (monotonic clock)."""
    for snap in snaps:
        sink.control_state(float(snap.t), snapshot_state(snap), hip_radius_m)
        for t, kind, text in snap.events:
            level = "warning" if kind in ("reaction", "space") or "fault" in text else "info"
            sink.event(float(t), level, kind, text)


def recording_summary(result: Mapping[str, Any]) -> str:
    """One line about a finished recording."""
    if result.get("error"):
        return f"recording: {result['error']}"
    size = result.get("bytes", 0) / 1e6
    dropped = result.get("dropped", 0)
    tail = f", {dropped} messages dropped (queue full)" if dropped else ""
    return f"wrote {result['path']} ({result.get('messages', 0)} messages, {size:.1f} MB{tail})"


__all__ = [
    "CONTROL_EVERY_TICKS",
    "demo_recorder",
    "frame_hook",
    "record_snapshots",
    "record_ticks",
    "recording_summary",
    "scene_recorder",
    "snapshot_state",
]
