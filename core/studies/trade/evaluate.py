"""One trial of a trade study: its knobs measured side by side on the same frames.

Every trial runs the perception pipeline configured by its knobs on the same rendered frames of
the same scenes (the HIP tracks of ``bench perception``), each scene with a fresh pipeline, and
measures latency from the depth frame and accuracy against the simulator's exact truth. A trial
with closed-loop knobs (fusion, haptics, controller) also runs a short deterministic closed loop
of a shipped scene and reports its true minimum margin and how far the fused surface tracked the
true one. Everything but the latency is deterministic: the same trial gives the same figures on
any machine.

A trial may also run on recordings (``TrialSpec.recordings``): each camera's recorded frames go,
in order, through a pipeline of their own with the trial's knobs, and are scored against the
reference the recording's reader gives each frame (:class:`StudyFrame`: the truth of a simulated
scene, or the estimate recorded for the frame; ``hapticloud.hardware.study.recording``).
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import ConfigError, HapticloudError
from ...perception import CameraPipeline, SurfaceEstimate
from ...scene import SceneConfig
from ...sim import BenchScene, ContactScene, contact_bench_scenes, perception_bench_scenes
from ...sim.depth_camera import SimDepthCamera
from ..perception import FRAME_RATE_HZ, NEAR_M, R_HIP_M, SEGMENT_FRAMES, hip_track
from .knobs import CAMERA_KNOBS, is_closed_loop, split_camera, with_companions

#: Objectives of every trial: name -> (what, better). Latency is from the depth frame; accuracy
#: is over the valid estimates against the truth at their HIP.
PERCEPTION_OBJECTIVES: dict[str, tuple[str, str]] = {
    "latency_ms_median": ("latency from the depth frame, median (ms)", "min"),
    "latency_ms_p90": ("latency from the depth frame, p90 (ms)", "min"),
    "centroid_mm_median": ("centroid error |c - c_true|, median (mm)", "min"),
    "centroid_mm_p90": ("centroid error, p90 (mm)", "min"),
    "d_proj_mm_p90": ("|d_proj error|, p90 (mm)", "min"),
    "normal_deg_median": ("normal error, median (deg)", "min"),
    "valid_share": ("valid estimates with the surface within 0.08 m", "max"),
}
#: Objectives of trials with closed-loop knobs.
LOOP_OBJECTIVES: dict[str, tuple[str, str]] = {
    "min_margin_mm": ("true minimum margin of the closed-loop run (mm)", "max"),
    "tracking_error_mm": ("fused surface vs the true one, centroid p90 (mm)", "min"),
}
OBJECTIVES = {**PERCEPTION_OBJECTIVES, **LOOP_OBJECTIVES}

#: A trial is unsafe when the closed loop's true margin went below this (mm; the verdict's
#: allowance) ...
UNSAFE_MARGIN_MM = -2.0
#: ... or when more than this share of the frames near the surface had no valid estimate.
MAX_INVALID_SHARE = 0.05
SEED = 7  #: the HIP tracks' seed (the one of ``bench perception``)
#: The shipped closed-loop scene and duration a closed-loop trial runs: the first impact on the
#: head at 0.5 m/s, two rendered cameras in the loop.
LOOP_SCENE = "impacts"
LOOP_DURATION_S = 1.5

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TrialSpec:
    """What one trial measures: its knobs, the scenes and frames, the closed-loop run."""

    params: Mapping[str, Any]
    scenes: tuple[str, ...]
    frames: int
    seed: int = SEED
    loop_scene: str = LOOP_SCENE
    loop_duration_s: float = LOOP_DURATION_S
    #: Raise the knobs' companions with them (:data:`~.knobs.COMPANIONS`); the extremes do not:
    #: a knob alone past its companion is a config the rules refuse, and that is the finding.
    companions: bool = True
    #: Recordings measured beside the scenes, each named by its reader's identity of the file
    #: (path and content digest, so the cache knows a changed file); ``frames`` per camera.
    recordings: tuple[str, ...] = ()

    @property
    def closed_loop(self) -> bool:
        return any(is_closed_loop(k) for k in self.params)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "params": dict(sorted(self.params.items())),
            "scenes": list(self.scenes),
            "frames": self.frames,
            "seed": self.seed,
        }
        if not self.companions:
            out["companions"] = False
        if self.recordings:
            out["recordings"] = list(self.recordings)
        if self.closed_loop:
            out["loop"] = {"scene": self.loop_scene, "duration_s": self.loop_duration_s}
        return out


@dataclass(frozen=True)
class TrialResult:
    """The figures of one trial (``objectives`` by name; NaN where not measured)."""

    params: Mapping[str, Any]
    objectives: Mapping[str, float]
    unsafe: bool
    reasons: tuple[str, ...] = ()
    worker: str = ""
    wall_s: float = 0.0
    frames: int = 0
    estimates: int = 0
    #: Per-frame problems: non-finite figures, valid estimates off their budget (extremes).
    problems: tuple[str, ...] = ()
    cached: bool = False
    extra: Mapping[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "params": dict(self.params),
            "objectives": {k: _json_number(v) for k, v in self.objectives.items()},
            "unsafe": self.unsafe,
            "reasons": list(self.reasons),
            "worker": self.worker,
            "wall_s": round(self.wall_s, 3),
            "frames_per_scene": self.frames,
            "estimates": self.estimates,
            "problems": list(self.problems),
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any], *, cached: bool = False) -> TrialResult:
        return cls(
            params=dict(data["params"]),
            objectives={
                k: (float("nan") if v is None else float(v)) for k, v in data["objectives"].items()
            },
            unsafe=bool(data["unsafe"]),
            reasons=tuple(data.get("reasons", ())),
            worker=str(data.get("worker", "")),
            wall_s=float(data.get("wall_s", 0.0)),
            frames=int(data.get("frames_per_scene", 0)),
            estimates=int(data.get("estimates", 0)),
            problems=tuple(data.get("problems", ())),
            cached=cached,
        )


def _json_number(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def shipped_default(key: str, loop_scene: str = LOOP_SCENE) -> Any:
    """The value a knob has when the study does not turn it: the parameter's default, or for a
    closed-loop knob the closed-loop scene's own value (a scene file tunes some, e.g. the
    impacts scene's stiffer fusion)."""
    if key in CAMERA_KNOBS:
        return CAMERA_KNOBS[key].default
    if is_closed_loop(key):
        from ...scene import load_scene

        return load_scene(loop_scene).config.get_path(key)
    return SceneConfig().get_path(key)


# ----- scenes and their frames -------------------------------------------------------------------
def study_scenes() -> dict[str, BenchScene]:
    """The scenes a study may use: the perception benchmark's eight and the training scenes where
    bodies meet (the held-out ones stay out of every tuning)."""
    return {**perception_bench_scenes(), **contact_bench_scenes("train")}


def check_scenes(names: Sequence[str]) -> tuple[str, ...]:
    known = study_scenes()
    for name in names:
        if name not in known:
            raise ConfigError(f"--scenes {name}: unknown scene (known: {', '.join(known)})")
    if not names:
        raise ConfigError("--scenes: no scene named")
    return tuple(dict.fromkeys(names))


@dataclass(frozen=True)
class StudyFrame:
    """One depth frame a trial's pipeline runs on, and the reference its estimate is scored
    against (``true_point`` ``None``: no reference for this frame, only its latency counts)."""

    t: float
    hip: FloatArray
    depth: Any  # DepthFrame
    occluders: tuple[Any, ...]
    true_point: FloatArray | None
    true_normal: FloatArray | None
    true_distance_m: float


#: ``(recording, frames per camera) -> {camera: frames}``: how a worker reads a recording's
#: frames (the hardware layer's reader; core reads no file).
RecordedFrames = Callable[[str, int], Mapping[str, Sequence[StudyFrame]]]


def _study_camera(camera: SimDepthCamera, decimation: int) -> SimDepthCamera:
    """The scene's camera rendering ``decimation`` times smaller images (``camera.decimation``)."""
    if decimation == camera.decimation:
        return camera
    if camera.decimation != 1:
        raise ConfigError(f"camera.decimation: {camera.name} is not a full-resolution camera")
    return SimDepthCamera(
        camera.name,
        camera.intrinsics,
        camera.pose_world_camera,
        camera.noise,
        decimation=decimation,
    )


# Rendering is 3-4x the cost of processing a frame and the same for every trial: each worker
# renders a scene's frames once (about 1.6 MB a frame; the default study holds ~200 frames).
@functools.lru_cache(maxsize=16)
def _frames(scene_name: str, frames: int, seed: int, decimation: int = 1) -> tuple[StudyFrame, ...]:
    names = list(study_scenes())
    scene = study_scenes()[scene_name]
    index = names.index(scene_name)
    if isinstance(scene, ContactScene):
        track = scene.hip_track(frames, seed + index, SEGMENT_FRAMES)
    else:
        track = hip_track(scene, frames, seed + index)
    camera = _study_camera(scene.cameras[0], decimation)
    out = []
    for i, hip in enumerate(track):
        t = i / FRAME_RATE_HZ
        occluders = tuple(scene.occluders(hip, t))
        truth = scene.world.ground_truth(hip, t)
        out.append(
            StudyFrame(
                t,
                np.asarray(hip, dtype=np.float64),
                camera.render(scene.world, t, occluders=occluders),
                occluders,
                np.asarray(truth.point, dtype=np.float64),
                np.asarray(truth.normal, dtype=np.float64),
                float(truth.distance_m),
            )
        )
    return tuple(out)


def _angle_deg(a: FloatArray, b: FloatArray) -> float:
    return float(np.degrees(np.arccos(np.clip(float(a @ b), -1.0, 1.0))))


def _median_p90(values: list[float]) -> tuple[float, float]:
    arr = np.asarray(values, dtype=np.float64)
    if arr.size == 0:
        return float("nan"), float("nan")
    return float(np.median(arr)), float(np.percentile(arr, 90))


# ----- evaluation --------------------------------------------------------------------------------
@dataclass
class _Tally:
    latency_ms: list[float] = field(default_factory=list)
    centroid_mm: list[float] = field(default_factory=list)
    normal_deg: list[float] = field(default_factory=list)
    dproj_mm: list[float] = field(default_factory=list)
    near: int = 0
    near_valid: int = 0
    estimates: int = 0
    problems: list[str] = field(default_factory=list)


def _check_estimate(
    est: SurfaceEstimate, errors: tuple[float, float, float], budget_mm: float | None
) -> str:
    """What is wrong with one estimate, or "" (see :func:`evaluate`'s ``budget_mm``)."""
    if not est.valid:
        return "" if est.reason else "invalid without a reason"
    if not all(math.isfinite(e) for e in errors):
        return "valid with a non-finite error"
    if budget_mm is not None and errors[2] > budget_mm:
        return (
            f"valid but the surface {errors[2]:+.1f} mm farther than it is (budget {budget_mm:g})"
        )
    return ""


def _params(spec: TrialSpec) -> dict[str, Any]:
    """The trial's scene configuration overrides (camera knobs apart, see :func:`_camera`)."""
    params = split_camera(spec.params)[0]
    return with_companions(params) if spec.companions else params


def _camera(spec: TrialSpec) -> dict[str, Any]:
    return split_camera(spec.params)[1]


def _streams(
    spec: TrialSpec, recorded_frames: RecordedFrames | None
) -> list[tuple[str, Sequence[StudyFrame]]]:
    """(label, frames) of every camera stream of the trial: the scenes', then the recordings'."""
    decimation = int(_camera(spec)["decimation"])
    out: list[tuple[str, Sequence[StudyFrame]]] = [
        (name, _frames(name, spec.frames, spec.seed, decimation)) for name in spec.scenes
    ]
    if spec.recordings and recorded_frames is None:
        raise ConfigError("recordings: this worker was given no reader for them")
    for rec in spec.recordings:
        assert recorded_frames is not None
        for camera, frames in recorded_frames(rec, spec.frames).items():
            out.append((f"{rec.split('#')[0]} {camera}", frames))
    return out


def _perceive(
    spec: TrialSpec, budget_mm: float | None, recorded_frames: RecordedFrames | None = None
) -> _Tally:
    cfg = SceneConfig().with_overrides(_params(spec)).perception
    tally = _Tally()
    for scene_name, frames in _streams(spec, recorded_frames):
        if not frames:
            continue
        pipe = CameraPipeline(cfg, camera=frames[0].depth.camera)
        for i, f in enumerate(frames):
            t0 = time.perf_counter()
            est = pipe.process_depth(f.depth, f.hip, exclude=f.occluders)
            tally.latency_ms.append((time.perf_counter() - t0) * 1e3)
            tally.estimates += 1
            if f.true_point is None or f.true_normal is None:
                # No reference: the estimate is only checked for being finite, or invalid with
                # its reason.
                centroid = est.centroid if est.valid else (0.0, 0.0, 0.0)
                problem = _check_estimate(est, tuple(float(x) for x in centroid), None)
                if problem:
                    tally.problems.append(f"{scene_name} frame {i}: {problem}")
                continue
            near = f.true_distance_m <= NEAR_M
            tally.near += near
            errors = (float("nan"),) * 3
            if est.valid:
                tally.near_valid += near
                d_true = f.true_distance_m - R_HIP_M
                errors = (
                    float(np.linalg.norm(est.centroid - f.true_point) * 1e3),
                    _angle_deg(est.normal, f.true_normal),
                    (est.d_proj(f.hip, R_HIP_M) - d_true) * 1e3,
                )
                tally.centroid_mm.append(errors[0])
                tally.normal_deg.append(errors[1])
                tally.dproj_mm.append(abs(errors[2]))
            problem = _check_estimate(est, errors, budget_mm)
            if problem:
                tally.problems.append(f"{scene_name} frame {i}: {problem}")
    return tally


def _closed_loop(spec: TrialSpec) -> dict[str, float]:
    from ..run import estimate_errors, run_scene

    rec = run_scene(spec.loop_scene, _params(spec), spec.loop_duration_s)
    margin = rec.arrays["margin"]
    fused = estimate_errors(rec)["fused"] if rec.info["cameras"] else {}
    tracking = fused.get("centroid_mm", {}).get("p90")
    return {
        "min_margin_mm": float(margin.min() * 1e3) if margin.size else float("nan"),
        "tracking_error_mm": float("nan") if tracking is None else float(tracking),
    }


def evaluate(
    spec: TrialSpec,
    *,
    budget_mm: float | None = None,
    recorded_frames: RecordedFrames | None = None,
) -> TrialResult:
    """Measure one trial (see the module docstring).

    ``budget_mm``: when given, a valid estimate that reports the surface farther than it is by
    more (d_proj error on the unsafe side; nearer is conservative) is a problem (the extremes'
    check). A config the parameters' rules refuse, or the closed-loop scene refuses to build
    with, is reported with its reason, not raised. ``recorded_frames`` reads the frames of
    ``spec.recordings``.
    """
    t0 = time.perf_counter()
    try:
        SceneConfig().with_overrides(_params(spec))
        if spec.recordings and _camera(spec)["decimation"] != 1:
            raise ConfigError("camera.decimation: a recording's frames cannot be rendered again")
    except ConfigError as err:
        return TrialResult(
            spec.params, dict.fromkeys(OBJECTIVES, float("nan")), True, (f"refused: {err}",)
        )
    tally = _perceive(spec, budget_mm, recorded_frames)
    lat_med, lat_p90 = _median_p90(tally.latency_ms)
    c_med, c_p90 = _median_p90(tally.centroid_mm)
    objectives = {
        "latency_ms_median": lat_med,
        "latency_ms_p90": lat_p90,
        "centroid_mm_median": c_med,
        "centroid_mm_p90": c_p90,
        "d_proj_mm_p90": _median_p90(tally.dproj_mm)[1],
        "normal_deg_median": _median_p90(tally.normal_deg)[0],
        "valid_share": tally.near_valid / tally.near if tally.near else float("nan"),
    }
    reasons = []
    loop = dict.fromkeys(LOOP_OBJECTIVES, float("nan"))
    if spec.closed_loop:
        try:
            loop = _closed_loop(spec)
        except HapticloudError as err:
            reasons.append(f"refused at build: {err}")
    objectives.update(loop)
    if tally.near and 1.0 - objectives["valid_share"] > MAX_INVALID_SHARE:
        reasons.append(
            f"{100 * (1 - objectives['valid_share']):.0f} % of the frames near the surface "
            f"invalid (limit {100 * MAX_INVALID_SHARE:.0f} %)"
        )
    if not math.isfinite(objectives["centroid_mm_p90"]):
        reasons.append("no valid estimate")
    if spec.closed_loop and not reasons:
        margin = objectives["min_margin_mm"]
        if not margin >= UNSAFE_MARGIN_MM:
            reasons.append(f"true margin {margin:+.1f} mm (allowed {UNSAFE_MARGIN_MM:g} mm)")
    return TrialResult(
        params=dict(spec.params),
        objectives=objectives,
        unsafe=bool(reasons),
        reasons=tuple(reasons),
        wall_s=time.perf_counter() - t0,
        frames=spec.frames,
        estimates=tally.estimates,
        problems=tuple(tally.problems),
    )


__all__ = [
    "LOOP_DURATION_S",
    "LOOP_OBJECTIVES",
    "LOOP_SCENE",
    "MAX_INVALID_SHARE",
    "OBJECTIVES",
    "PERCEPTION_OBJECTIVES",
    "SEED",
    "UNSAFE_MARGIN_MM",
    "RecordedFrames",
    "StudyFrame",
    "TrialResult",
    "TrialSpec",
    "check_scenes",
    "evaluate",
    "shipped_default",
    "study_scenes",
]
