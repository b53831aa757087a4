"""Recordings as a trade study's source: their frames, and the reference each is scored against.

A trial re-runs perception on a recording's depth frames (each camera's in order, through a
pipeline of its own, as ``hapticloud replay`` does) with its knobs. What a frame's estimate is
scored against depends on what the recording knows:

- **the truth**, when it was made by the simulator on the scene clock (``run``, whose metadata
  hold the scene's TOML): the scene is built again and the true closest surface point (bodies
  and walls) at the frame's HIP and time is computed, exactly as the run's own truth;
- otherwise (``demo``, ``run --hardware``, the app, an imported bag) **the recorded estimates**,
  made with the recorded parameters: the figures then say how far the trial's estimates are
  from those, an agreement and not an accuracy; frames whose recorded estimate is invalid have
  no reference (only their latency counts).

A recording is named by :func:`recording_id` (its path and a digest of its content), so the
trial cache knows a changed file. The path must be readable where the trial runs (a worker of a
remote cluster reads it itself).
"""

from __future__ import annotations

import functools
import hashlib
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from hapticloud.core.errors import ConfigError
from hapticloud.core.studies.trade.evaluate import StudyFrame

from ..recording import format as fmt
from ..recording.reader import Recording

#: Bytes read from each end of a file for its digest (a recording's chunks all differ).
_DIGEST_BYTES = 1 << 20


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    size = path.stat().st_size
    h.update(str(size).encode())
    with path.open("rb") as f:
        h.update(f.read(_DIGEST_BYTES))
        if size > 2 * _DIGEST_BYTES:
            f.seek(size - _DIGEST_BYTES)
            h.update(f.read(_DIGEST_BYTES))
        else:
            h.update(f.read())
    return h.hexdigest()[:16]


def recording_id(path: str | Path) -> str:
    """``"ABSOLUTE_PATH#DIGEST"``: opens the file once (a bad one is a one-line
    :class:`~hapticloud.core.errors.RecordingError`) and digests its content."""
    p = Path(path).expanduser().resolve()
    with Recording.open(p) as rec:
        if not rec.cameras:
            raise ConfigError(f"--recording {path}: no camera frames to re-run perception on")
    return f"{p}#{_digest(p)}"


def _scene_truth(rec: Recording) -> tuple[object, str] | None:
    """The rebuilt scene's assembly and its name, when the recording has the simulator's truth."""
    from hapticloud.core.scene.assembly import assemble
    from hapticloud.core.scene.loader import parse_scene

    scene_meta = rec.metadata.get(fmt.SCENE_METADATA, {})
    if rec.info.get("clock") != "scene" or not scene_meta.get("toml"):
        return None
    scene = parse_scene(tomllib.loads(scene_meta["toml"]), scene_meta.get("path", "<recording>"))
    return assemble(scene), scene.name


def reference(path: str | Path) -> str:
    """What the frames of the recording at ``path`` are scored against (one phrase)."""
    with Recording.open(Path(str(path).split("#")[0])) as rec:
        scene_meta = rec.metadata.get(fmt.SCENE_METADATA, {})
        if rec.info.get("clock") == "scene" and scene_meta.get("toml"):
            return f"the simulator's truth (scene {scene_meta.get('name', '?')} rebuilt)"
    return (
        "the recorded estimates, made with the recorded parameters (no truth recorded: the "
        "figures are the trial's agreement with them, not an accuracy)"
    )


@functools.lru_cache(maxsize=4)
def _load(rec_id: str, frames: int) -> Mapping[str, tuple[StudyFrame, ...]]:
    path = Path(rec_id.split("#")[0])
    out: dict[str, list[StudyFrame]] = {}
    with Recording.open(path) as rec:
        truth = _scene_truth(rec)
        recorded = {} if truth else {(e.camera, e.seq): e for e in rec.estimates()}
        cameras = rec.cameras
        for cap in rec.frames(cameras):
            stream = out.setdefault(cap.camera, [])
            if len(stream) >= frames:
                if all(len(out.get(c, ())) >= frames for c in cameras):
                    break
                continue
            hip = np.asarray(cap.hip, dtype=np.float64)
            point = normal = None
            distance = float("nan")
            if truth is not None:
                margin, _, _, p, n, _ = truth[0].true_margin(hip, cap.frame.t)  # type: ignore[attr-defined]
                point, normal = np.asarray(p, np.float64), np.asarray(n, np.float64)
                distance = float(margin) + float(truth[0].hip_radius_m)  # type: ignore[attr-defined]
            else:
                est = recorded.get((cap.camera, cap.seq))
                if est is not None and est.valid:
                    point = np.asarray(est.centroid, np.float64)
                    normal = np.asarray(est.normal, np.float64)
                    # The distance the recorded estimate reported along its normal, so the
                    # trial's d_proj error is the difference of the two estimates' d_proj.
                    distance = float((hip - point) @ normal)
            stream.append(
                StudyFrame(cap.frame.t, hip, cap.frame, tuple(cap.exclude), point, normal, distance)
            )
    return {camera: tuple(stream) for camera, stream in out.items()}


def recorded_frames(rec_id: str, frames: int) -> Mapping[str, Sequence[StudyFrame]]:
    """The first ``frames`` frames of each camera of the recording ``rec_id`` (see
    :func:`recording_id`) with their references; read once per worker."""
    return _load(rec_id, frames)


__all__ = ["recorded_frames", "recording_id", "reference"]
