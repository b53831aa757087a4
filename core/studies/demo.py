"""The simulated demo scene, frame by frame: each camera's estimate against ground truth.

The patient's right hand, in the exoskeleton, reaches from in front of the chest to the face and
back (4 s per cycle); the two simulated D435s (front, 45 deg right) are interleaved at 30 Hz each
and see the robot's end effector in front of the surface. This is what ``hapticloud demo`` prints
until the app shows it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..perception import CameraPipeline, SurfaceEstimate
from ..sim import GroundTruth, SimScene, demo_scene, end_effector
from .perception import R_HIP_M, perception_config

CAMERA_RATE_HZ = 30.0
REACH_PERIOD_S = 4.0
CHEST_HIP = np.array([0.26, -0.06, 0.98])
FACE_HIP = np.array([0.15, -0.01, 1.21])
# The end effector's handle leaves the HIP forward-right and down, like the exoskeleton's forearm.
DEMO_HANDLE_DIRECTION = (0.35, -0.6, -0.7)


@dataclass(frozen=True)
class DemoFrame:
    """One camera frame of the demo: the estimate, the truth and the errors."""

    t: float
    hip: np.ndarray
    estimate: SurfaceEstimate
    truth: GroundTruth
    centroid_error_mm: float
    normal_error_deg: float
    d_proj_m: float
    d_proj_true_m: float
    latency_ms: float


def hip_at(t: float) -> np.ndarray:
    """The reaching HIP path: chest -> face -> chest, smooth (cosine) in time."""
    s = 0.5 - 0.5 * math.cos(2.0 * math.pi * t / REACH_PERIOD_S)
    return (1.0 - s) * CHEST_HIP + s * FACE_HIP


def demo_frames(
    duration_s: float,
    overrides: Mapping[str, Any] | None = None,
    scene: SimScene | None = None,
    frame_sink: Callable[..., None] | None = None,
) -> Iterator[DemoFrame]:
    """Yield every camera frame of ``duration_s`` seconds of the demo, in time order
    (``frame_sink``: called with ``(frame, hip, exclude, estimate)`` of each, e.g. a recorder)."""
    scene = demo_scene() if scene is None else scene
    config = perception_config(overrides)
    pipes = {cam.name: CameraPipeline(config, camera=cam.name) for cam in scene.cameras}
    period = 1.0 / CAMERA_RATE_HZ
    n_frames = int(duration_s / period)
    for k in range(n_frames):
        for j, camera in enumerate(scene.cameras):
            # Interleaved: the second camera fires half a period after the first.
            t = k * period + j * period / len(scene.cameras)
            hip = hip_at(t)
            occluders = end_effector(hip, np.asarray(DEMO_HANDLE_DIRECTION))
            # Only the pixels the crop reads are ray-cast (the full render's frame there, 0
            # elsewhere); a recorder (frame_sink) may store more of the image: the whole frame.
            roi = None if frame_sink is not None else camera.workspace_roi(hip, config.crop)
            frame = camera.render(scene.world, t, occluders=occluders, roi=roi)
            est = pipes[camera.name].process_depth(frame, hip, exclude=occluders)
            if frame_sink is not None:
                frame_sink(frame, hip, occluders, est)
            truth = scene.world.ground_truth(hip, t)
            d_true = truth.distance_m - R_HIP_M
            if est.valid:
                c_err = float(np.linalg.norm(est.centroid - truth.point) * 1e3)
                cos = float(np.clip(est.normal @ truth.normal, -1.0, 1.0))
                n_err = math.degrees(math.acos(cos))
                d_est = est.d_proj(hip, R_HIP_M)
            else:
                c_err = n_err = d_est = float("nan")
            yield DemoFrame(
                t=t,
                hip=hip,
                estimate=est,
                truth=truth,
                centroid_error_mm=c_err,
                normal_error_deg=n_err,
                d_proj_m=d_est,
                d_proj_true_m=d_true,
                latency_ms=float(est.stage_ms.get("total", float("nan"))),
            )
