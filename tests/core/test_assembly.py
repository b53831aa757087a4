"""The scene's parts, each builder alone and :func:`assemble` as the closed loop uses it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hapticloud.core.errors import ConfigError
from hapticloud.core.fusion import SurfaceFusion
from hapticloud.core.loop import HapticLoop
from hapticloud.core.perception import CameraPipeline
from hapticloud.core.scene import load_scene, parse_scene
from hapticloud.core.scene.assembly import (
    InfeasibleSceneError,
    assemble,
    build_cameras,
    build_fusion,
    build_loop,
    build_patient,
    build_pipeline,
    build_robot,
    build_scene_controller,
    build_walls,
    build_world,
    camera_pose,
    check_start,
    initial_joints,
    scene_controller_config,
    seeded_noise,
)
from hapticloud.core.sim.closed_loop import ClosedLoopSim, build_plant
from hapticloud.core.sim.depth_camera import SimDepthCamera

HIP0 = [0.30, 0.10, 1.00]
FLOOR = {"name": "floor", "point_m": [0.3, 0.1, 0.80], "normal": [0.0, 0.0, 1.0]}
ORACLES = {"cameras.front.model": "oracle", "cameras.right45.model": "oracle"}


def _scene(**tables):
    data = {"scene": {"name": "t"}, "robot": {"hip0_m": HIP0}, "walls": [FLOOR]}
    data.update(tables)
    return parse_scene(data, "t.toml")


def test_robot_and_start_posture() -> None:
    scene = _scene()
    robot = build_robot(scene)
    q0 = initial_joints(scene, robot)
    assert q0.shape == (robot.n_joints,)
    np.testing.assert_allclose(robot.hip_position_at(q0), HIP0, atol=1e-4)
    home = parse_scene({"scene": {"name": "home"}}, "home.toml")
    np.testing.assert_array_equal(initial_joints(home, robot), robot.q_home)
    far = _scene(robot={"hip0_m": [1.5, 0.0, 1.0]})
    with pytest.raises(InfeasibleSceneError, match="out of the robot's reach"):
        initial_joints(far, robot)
    short = _scene(robot={"q0_rad": [0.0, 0.0]})
    with pytest.raises(ConfigError, match="expected 6 joint positions, got 2"):
        initial_joints(short, robot)


def test_world_places_the_moving_surface_from_the_start_hip() -> None:
    scene = load_scene("moving-surface")
    hip0 = np.array([0.45, 0.0, 0.95])
    world = build_world(scene, hip0)
    surface = scene.config.surface
    assert [b.name for b, _ in world.bodies] == [surface.name]
    assert world.background and world.moving == world.bodies
    d, _, normal, idx = world.closest(hip0, 0.0)
    assert idx == 0
    r = scene.config.robot.hip_radius_m
    assert d == pytest.approx(r + surface.start_gap_m)
    # It faces the HIP and moves towards it along its direction from start_s, at its speed.
    direction = np.array(surface.direction) / np.linalg.norm(surface.direction)
    np.testing.assert_allclose(normal, direction, atol=1e-9)
    d_later = world.closest(hip0, surface.start_s + 0.1)[0]
    assert d_later == pytest.approx(d - 0.1 * surface.speed_mps)
    # Without bodies there is no world to render.
    assert build_world(_scene(), hip0).at(0.0) is None


def test_named_placements_stand_around_the_target_and_left45_mirrors_right45() -> None:
    hip0 = np.array(HIP0)
    cameras = [
        {"name": name, "placement": name, "distance_m": 0.7, "height_m": 0.6}
        for name in ("front", "right45", "left45")
    ]
    ball = {"name": "head", "type": "sphere", "center_m": [0.0, 0.1, 1.0], "radius_m": 0.1}
    scene = _scene(cameras=cameras, bodies=[ball])
    eyes = {}
    for spec in scene.cameras:
        pose = camera_pose(spec, hip0)  # no target_m: the camera looks at the initial HIP
        eyes[spec.name] = pose[:3, 3] - hip0
        # The optical axis (camera +z) goes through the target.
        np.testing.assert_allclose(
            pose[:3, 2], -eyes[spec.name] / np.linalg.norm(eyes[spec.name]), atol=1e-12
        )
    np.testing.assert_allclose(eyes["front"], [0.7, 0.0, 0.6], atol=1e-12)
    s = 0.7 / np.sqrt(2.0)
    np.testing.assert_allclose(eyes["right45"], [s, -s, 0.6], atol=1e-12)  # the patient's right
    np.testing.assert_allclose(eyes["left45"], [s, s, 0.6], atol=1e-12)


def test_walls_keep_their_levels() -> None:
    walls = build_walls(_scene(walls=[FLOOR, {**FLOOR, "name": "stop", "level": "fixed"}]))
    assert [(w.name, w.level) for w in walls] == [("floor", "haptic"), ("stop", "fixed")]
    assert isinstance(walls, tuple)


def test_cameras_are_interleaved_aimed_and_have_their_own_pipelines() -> None:
    scene = load_scene("impacts", {"cameras.right45.model": "oracle"})
    hip0 = np.array([0.293, 0.005, 1.29])
    front, right = build_cameras(scene, hip0)
    assert front.phase_s == 0.0
    assert right.phase_s == pytest.approx(1.0 / (30.0 * 2))
    assert isinstance(front.camera, SimDepthCamera)
    np.testing.assert_array_equal(front.camera.pose_world_camera, camera_pose(front.spec, hip0))
    assert isinstance(front.pipeline, CameraPipeline) and front.pipeline.camera == "front"
    assert right.camera is None and right.pipeline is None  # an oracle perceives nothing
    assert right.oracle_reach_m == scene.config.perception.crop.workspace_radius_m
    assert build_pipeline(scene, front.spec) is not front.pipeline
    tiny = load_scene("impacts", {"cameras.front.decimation": 16, "cameras.front.width_px": 64})
    with pytest.raises(ConfigError, match=r"cameras\[front\].decimation: image too small"):
        build_cameras(tiny, hip0)


def test_fusion_controller_and_loop() -> None:
    scene = _scene()
    robot = build_robot(scene)
    walls = build_walls(scene)
    assert build_fusion(scene, ()) is None
    fusion = build_fusion(scene, build_cameras(load_scene("impacts"), np.array(HIP0)))
    assert isinstance(fusion, SurfaceFusion)
    # Fixed walls keep the HIP sphere out unless the scene sets their margin.
    assert scene_controller_config(scene).walls.margin_m == scene.config.robot.hip_radius_m
    own = _scene(controller={"walls": {"margin_m": 0.01}})
    assert scene_controller_config(own).walls.margin_m == 0.01
    controller = build_scene_controller(scene, robot, walls)
    loop = build_loop(scene, robot, controller, None, walls)
    assert isinstance(loop, HapticLoop)
    assert loop.controller is controller and loop.robot is robot and loop.fusion is None
    assert loop.dt == 1.0 / scene.config.loop.rate_hz
    assert loop.walls == walls  # haptic ones only: the floor is haptic


def test_patient_only_when_declared() -> None:
    hip0 = np.array(HIP0)
    assert build_patient(_scene(), np.zeros(6), hip0) is None
    scene = load_scene("wall")
    patient = build_patient(scene, np.zeros(6), hip0)
    assert patient is not None
    np.testing.assert_allclose(patient.intent.position(0.0), hip0)  # frame = hip0
    pressed = hip0 + np.array([0.0, 0.0, -0.23])  # the first impact's aim, after hold and travel
    np.testing.assert_allclose(patient.intent.position(0.3 + 0.23 / 0.5), pressed)
    back_in_time = [{"position_m": [0, 0, 0], "t_s": 1.0}, {"position_m": [0, 0, 0.1], "t_s": 0.5}]
    bad = _scene(patient={"waypoints": back_in_time})
    with pytest.raises(ConfigError, match=r"patient.waypoints\[1\].t_s = 0.5: must be after"):
        build_patient(bad, np.zeros(6), hip0)


def test_check_start_refuses_a_hip_inside_a_surface() -> None:
    scene = _scene()
    world, walls = build_world(scene, np.array(HIP0)), build_walls(scene)
    check_start(world, walls, 0.04, np.array(HIP0))
    with pytest.raises(InfeasibleSceneError, match=r"starts 10.0 mm inside a surface"):
        check_start(world, walls, 0.04, np.array([0.3, 0.1, 0.83]))


def test_assemble_composes_the_builders() -> None:
    scene = load_scene("impacts", ORACLES)
    parts = assemble(scene)
    robot = build_robot(scene)
    q0 = initial_joints(scene, robot)
    np.testing.assert_array_equal(parts.q0, q0)
    np.testing.assert_array_equal(parts.hip0, robot.hip_position_at(q0))
    assert [c.spec.name for c in parts.cameras] == ["front", "right45"]
    assert [c.phase_s for c in parts.cameras] == [
        c.phase_s for c in build_cameras(scene, parts.hip0)
    ]
    assert parts.loop.robot is parts.robot and parts.loop.controller is parts.controller
    assert parts.loop.fusion is parts.fusion is not None
    assert parts.patient is not None and parts.dt == 1.0 / 800.0
    assert parts.true_margin(parts.hip0, 0.0)[0] > 0.0
    # Each assembly is its own (the parts keep state).
    again = assemble(scene)
    assert again.loop is not parts.loop and again.fusion is not parts.fusion


def test_the_closed_loop_runs_on_the_assembly_as_it_ran_on_its_own_parts() -> None:
    scene = load_scene("impacts", ORACLES)
    parts = assemble(scene)
    sim = ClosedLoopSim(parts)
    assert sim.parts is parts and sim.loop is parts.loop and sim.robot is parts.robot
    assert sim.fusion is parts.fusion and sim.patient is parts.patient
    assert sim.walls is parts.walls and sim.world is parts.world
    assert sim.cameras == list(parts.cameras) and sim.q0 is parts.q0
    assert sim.plant.model is not parts.robot  # the plant integrates its own model
    a = sim.run(0.4)
    b = ClosedLoopSim(scene).run(0.4)
    for key in ("hip", "tau", "q", "margin", "fused_centroid", "status"):
        np.testing.assert_array_equal(a.arrays[key], b.arrays[key])
    assert [f.centroid.tolist() for f in a.frames] == [f.centroid.tolist() for f in b.frames]


def test_oracle_capture_draws_from_the_given_stream() -> None:
    parts = assemble(load_scene("impacts", ORACLES))
    cam = parts.cameras[0]
    _, true_point, normal, _ = parts.world.closest(parts.hip0, 0.0)
    near = true_point + 0.05 * normal
    first = parts.capture(cam, 0.0, parts.q0, near, seeded_noise(parts.scene))
    again = parts.capture(cam, 0.0, parts.q0, near, seeded_noise(parts.scene))
    assert first.valid and np.array_equal(first.centroid, again.centroid)
    direct = parts.oracle_estimate(cam, 0.0, near, seeded_noise(parts.scene))
    assert np.array_equal(direct.centroid, first.centroid)
    assert 0.0 < np.linalg.norm(first.centroid - true_point) < 0.01  # the truth, with noise
    # Nothing within its reach: a proof of free space, up to the reach.
    out = parts.capture(cam, 0.0, parts.q0, parts.hip0, seeded_noise(parts.scene))
    assert not out.valid and "nothing in range" in out.reason
    assert out.free_m == cam.oracle_reach_m


def test_plant_from_the_scene() -> None:
    scene = load_scene("wall")
    parts = assemble(scene)
    plant = build_plant(scene, build_robot(scene), parts.q0, held=True)
    assert plant.dt == 1.0 / 800.0 and plant.substeps == scene.config.loop.substeps
    assert plant.hand_mass_kg == scene.config.patient.mass_kg
    assert build_plant(scene, build_robot(scene), parts.q0, held=False).hand_mass_kg == 0.0
    assert plant.friction == scene.config.robot.joint_friction_nms_per_rad
    assert build_plant(scene, build_robot(scene), parts.q0, held=True, substeps=1).substeps == 1
    np.testing.assert_array_equal(plant.q, parts.q0)
    assert plant.q is not parts.q0


def test_builders_import_no_hardware_or_gui() -> None:
    code = (
        "import sys\n"
        "import hapticloud.core.scene.assembly\n"
        "roots = ('hapticloud.hardware', 'hapticloud.app', 'PyQt6', 'pyvista', 'can')\n"
        "bad = sorted(n for n in sys.modules if n.startswith(roots) and "
        "(n in roots or n.startswith(tuple(r + '.' for r in roots))))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
