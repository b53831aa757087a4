"""Simulated D435 frames for the perception: the full image vs only its region of interest.

Renders ``--frames`` frames of each camera of the demo scene (``assets/scenes/demo.toml``, built
as :func:`~hapticloud.core.scene.assembly.assemble` builds it) at decimation 1 and 2 (the
scene's default), the HIP moving along the patient's scripted reach with the robot's link capsules
(inverse kinematics at that HIP) as occluders. Each frame is rendered twice in turn, by two
separate cameras (so neither reuses the other's ray-cast caches): the whole image, and only the
workspace sphere's rectangle (``SimDepthCamera.workspace_roi`` with the scene's crop settings).
The first ``--warmup`` frames (scene BVH builds, the static room's one cast) are not timed. It
checks that the ROI frame is the full frame, bit for bit, inside the ROI and prints the medians
(and p90) of both and their ratio; the 3 ms target is checked at the scene's own decimation.

    .venv/bin/python benchmarks/camera_roi.py
    .venv/bin/python benchmarks/camera_roi.py --frames 200 --json /tmp/camera_roi.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import numpy as np
from hapticloud.core.scene import load_scene
from hapticloud.core.scene.assembly import Assembly, assemble, build_cameras
from hapticloud.core.sim.depth_camera import SimDepthCamera
from hapticloud.core.sim.exo import solve_hip_ik
from hapticloud.core.threads import settle_numerics

TARGET_ROI_MS = 3.0


def _cameras(parts: Assembly, decimation: int) -> list[SimDepthCamera]:
    """The scene's d435 cameras at ``decimation``, built as the assembly builds them."""
    names = [cam.spec.name for cam in parts.cameras if cam.spec.model == "d435"]
    scene = parts.scene.with_overrides({f"cameras.{n}.decimation": decimation for n in names})
    return [cam.camera for cam in build_cameras(scene, parts.hip0) if cam.spec.name in names]


def _stats(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90))}


def run(frames: int, warmup: int, decimations: list[int]) -> dict[str, Any]:
    settle_numerics(1)  # one BLAS thread, as the perception process runs
    sim = assemble(load_scene("demo"))
    crop = sim.scene.config.perception.crop
    rate = sim.scene.cameras[0].rate_hz
    assert sim.patient is not None  # the demo scripts the patient's reach
    # The HIPs and the robot along the reach, solved once (not timed).
    track = []
    q = sim.q0
    for i in range(warmup + frames):
        t = i / rate
        hip = sim.patient.intent.position(t)
        q, _ = solve_hip_ik(sim.robot, hip, q)
        track.append((t, hip, sim.robot.link_capsules(q)))
    results: dict[str, Any] = {
        "frames": frames,
        "scene": "demo",
        "shipped_decimation": sim.scene.cameras[0].decimation,
        "cameras": {},
    }
    for decimation in decimations:
        full_cams = _cameras(sim, decimation)
        roi_cams = _cameras(sim, decimation)
        for full_cam, roi_cam in zip(full_cams, roi_cams, strict=True):
            k = full_cam.intrinsics
            full_ms: list[float] = []
            roi_ms: list[float] = []
            roi_share: list[float] = []
            identical = True
            for i, (t, hip, capsules) in enumerate(track):
                world = sim.world.at(t)
                t0 = time.perf_counter()
                full = full_cam.render(world, t, occluders=capsules)
                t1 = time.perf_counter()
                roi = roi_cam.workspace_roi(hip, crop)
                part = roi_cam.render(world, t, occluders=capsules, roi=roi)
                t2 = time.perf_counter()
                r0, r1, c0, c1 = roi
                identical &= np.array_equal(full.depth_m[r0:r1, c0:c1], part.depth_m[r0:r1, c0:c1])
                if i >= warmup:
                    full_ms.append((t1 - t0) * 1e3)
                    roi_ms.append((t2 - t1) * 1e3)
                    roi_share.append((r1 - r0) * (c1 - c0) / (k.width * k.height))
            key = f"{full_cam.name}@dec{decimation}"
            results["cameras"][key] = {
                "decimation": decimation,
                "image": [k.width, k.height],
                "full_ms": _stats(full_ms),
                "roi_ms": _stats(roi_ms),
                "roi_pixels_share_median": float(np.median(roi_share)),
                "identical_inside_roi": bool(identical),
            }
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=100, help="timed frames per camera")
    parser.add_argument("--warmup", type=int, default=5, help="untimed frames first")
    parser.add_argument("--decimation", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--json", help="also write the figures here")
    args = parser.parse_args(argv)
    if args.frames < 1 or args.warmup < 0:
        parser.error("--frames must be >= 1 and --warmup >= 0")
    res = run(args.frames, args.warmup, args.decimation)
    print(f"demo scene, {args.frames} frames per camera (after {args.warmup} untimed), ms")
    print(
        f"{'camera':16s} {'image':>9s}  {'full med/p90':>14s}  {'ROI med/p90':>12s}  "
        f"{'ratio':>6s}  {'ROI px':>6s}  same"
    )
    ok = True
    for name, r in res["cameras"].items():
        full, roi = r["full_ms"], r["roi_ms"]
        ratio = full["median"] / roi["median"]
        size = f"{r['image'][0]}x{r['image'][1]}"
        same = "yes" if r["identical_inside_roi"] else "NO"
        print(
            f"{name:16s} {size:>9s}  {full['median']:6.2f}/{full['p90']:6.2f}  "
            f"{roi['median']:5.2f}/{roi['p90']:5.2f}  {ratio:5.1f}x  "
            f"{100 * r['roi_pixels_share_median']:5.1f}%  {same}"
        )
        ok &= r["identical_inside_roi"]
    # The target is for the scene as shipped (its decimation); other decimations are shown.
    shipped = res["shipped_decimation"]
    at = [r["roi_ms"]["median"] for r in res["cameras"].values() if r["decimation"] == shipped]
    if at:
        worst = max(at)
        verdict = "PASS" if worst <= TARGET_ROI_MS else "FAIL"
        print(
            f"[{verdict}] ROI render <= {TARGET_ROI_MS:g} ms median at decimation {shipped} "
            f"(the demo's): worst camera {worst:.2f} ms"
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=2)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
