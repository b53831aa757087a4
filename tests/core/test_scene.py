"""Scene files: schema validation (one-line errors naming file and key), overrides, shipped scenes,
and "only what the scene declares is built"."""

from __future__ import annotations

from pathlib import Path

import pytest
from hapticloud.core.errors import ConfigError
from hapticloud.core.scene import load_scene, parse_scene, resolve_scene, scenes_dir
from hapticloud.core.sim.closed_loop import ClosedLoopSim, InfeasibleSceneError

SHIPPED = ("impacts", "sliding", "wall", "moving-surface", "demo")

MINIMAL = """
[scene]
name = "t"
duration_s = 0.5

[robot]
hip0_m = [0.30, 0.10, 1.00]

[[walls]]
name = "floor"
point_m = [0.3, 0.1, 0.80]
normal = [0.0, 0.0, 1.0]
"""


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_scene_loads(name: str) -> None:
    scene = load_scene(name)
    assert scene.name == name
    assert resolve_scene(f"{name}.toml") == scenes_dir() / f"{name}.toml"


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        ("[robot]\nhip_radiu_m = 0.04\n", r"robot\.hip_radiu_m: unknown key"),
        ('[robot]\nhip_radius_m = "big"\n', r"robot\.hip_radius_m = 'big': expected a number"),
        (
            "[robot]\nhip_radius_m = -0.01\n",
            r"robot\.hip_radius_m = -0\.01: must be in \[0\.0, 0\.2\]",
        ),
        ("[haptics.velocity]\nkv = 0.0\n", r"haptics\.velocity\.kv = 0\.0: must be in"),
        ("[loop]\nsubsteps = 2.5\n", r"loop\.substeps = 2\.5: expected an integer"),
        ("[bogus]\nx = 1\n", r"bogus: unknown key"),
        (
            '[[cameras]]\nname = "c"\ndecimaton = 2\n[[bodies]]\nname = "b"\nradius_m = 0.1\n'
            "center_m = [0, 0, 1]\n",
            r"cameras\[0\]\.decimaton: unknown key",
        ),
        ('[[bodies]]\nname = "b"\ntype = "cube"\n', r"bodies\[0\]\.type = 'cube': must be one of"),
        (
            '[[bodies]]\nname = "b"\ntype = "sphere"\ncenter_m = [0, 0, 1]\n',
            r"bodies\[0\]\.radius_m: a sphere needs",
        ),
        ('[[walls]]\nname = "w"\npoint_m = [0, 0]\nnormal = [0, 0, 1]\n', r"walls\[1\]\.point_m"),
        ('[[walls]]\nname = "w"\npoint_m = [0,0,0]\nnormal = [0, 0, 0]\n', r"non-zero direction"),
        ('[[cameras]]\nname = "c"\n', r"cameras: the scene has cameras but nothing to see"),
    ],
)
def test_bad_scene_files_give_one_line_errors_naming_file_and_key(
    tmp_path: Path, extra: str, needle: str
) -> None:
    text = MINIMAL + extra
    if extra.startswith("[robot]"):  # a second [robot] table is a TOML error: merge instead
        text = MINIMAL.replace(
            "[robot]\n", extra.splitlines()[0] + "\n" + extra.splitlines()[1] + "\n"
        )
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError, match=needle) as info:
        load_scene(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(str(path))


def test_missing_file_and_bad_toml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such scene file"):
        load_scene(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scene(_write(tmp_path, "[scene\n"))


def test_overrides_reach_tables_and_named_entries(tmp_path: Path) -> None:
    scene = load_scene(
        "impacts",
        {
            "haptics.positional.kp": 20.0,
            "cameras.front.decimation": 4,
            "cameras.1.latency_s": 0.03,
            "patient.waypoints.1.speed_mps": 0.7,
        },
    )
    assert scene.config.haptics.positional.kp == 20.0
    assert scene.cameras[0].decimation == 4 and scene.cameras[1].latency_s == 0.03
    assert scene.waypoints[1].speed_mps == 0.7
    with pytest.raises(ConfigError, match="declares no \\[surface\\]"):
        load_scene("impacts", {"surface.speed_mps": 2.0})
    with pytest.raises(ConfigError, match="no cameras entry 'top'"):
        load_scene("impacts", {"cameras.top.decimation": 1})
    with pytest.raises(ConfigError, match=r"with --set robot\.hip_radius_m.*must be in"):
        load_scene("wall", {"robot.hip_radius_m": 5.0})


def test_duplicate_names_and_conflicting_keys() -> None:
    base = {"robot": {"hip0_m": [0.3, 0.1, 1.0]}}
    wall = {"point_m": [0, 0, 0.8], "normal": [0, 0, 1]}
    with pytest.raises(ConfigError, match="walls: names must be unique"):
        parse_scene({**base, "walls": [{"name": "w", **wall}, {"name": "w", **wall}]})
    with pytest.raises(ConfigError, match="q0_rad, hip0_m: give one"):
        parse_scene({"robot": {"hip0_m": [0.3, 0.1, 1.0], "q0_rad": [0, 0, 0, 0, 0, 0]}})


def test_only_what_the_scene_declares_is_built(tmp_path: Path) -> None:
    sim = ClosedLoopSim(load_scene(_write(tmp_path, MINIMAL)))
    assert sim.cameras == [] and sim.fusion is None and sim.loop.fusion is None
    assert sim.patient is None and sim.world.bodies == []
    one = load_scene("impacts", {"cameras.right45.model": "oracle"})
    data = dict(one.data)
    data["cameras"] = data["cameras"][:1]
    single = ClosedLoopSim(parse_scene(data, "one-camera"))
    assert len(single.cameras) == 1 and single.fusion is not None


def test_unreachable_start_is_infeasible_not_a_crash(tmp_path: Path) -> None:
    path = _write(tmp_path, MINIMAL.replace("[0.30, 0.10, 1.00]", "[1.5, 0.0, 1.0]"))
    with pytest.raises(InfeasibleSceneError, match="out of the robot's reach"):
        ClosedLoopSim(load_scene(path))
    inside = _write(tmp_path, MINIMAL.replace("0.80]", "0.99]"))
    with pytest.raises(InfeasibleSceneError, match=r"starts .* inside a surface"):
        ClosedLoopSim(load_scene(inside))
