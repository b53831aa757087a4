"""``hapticloud study``: bad input refused before anything starts; a small grid on an embedded
LocalCluster of one worker, with its JSON, plots and presets; a rerun read from the cache."""

from __future__ import annotations

import json
import socket
import tomllib
from pathlib import Path

import pytest
from hapticloud.app import cli
from hapticloud.hardware.live.contract import LiveConfig

VOXEL = "perception.voxel.voxel_size_m"


@pytest.fixture
def no_cluster(monkeypatch: pytest.MonkeyPatch) -> None:
    """Bad input must be refused before a cluster is started."""
    from hapticloud.hardware.study import cluster

    def refuse(*_a: object, **_k: object) -> None:
        raise AssertionError("a cluster was started for bad input")

    monkeypatch.setattr(cluster, "open_client", refuse)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--grid", "perception.voxel.size=0.004"], "unknown knob"),
        (["--grid", f"{VOXEL}=0.2"], "must be in [0.0005, 0.05]"),
        (["--grid", f"{VOXEL}="], "empty grid"),
        (
            [
                "--grid",
                f"{VOXEL}={','.join(str(0.001 + i * 1e-05) for i in range(101))}",
                "--grid",
                "perception.abstraction.quadric.bandwidth_m="
                + ",".join(str(0.01 + i * 0.0001) for i in range(100)),
            ],
            "over 10,000; add --yes",
        ),
        (["--search", "nsga2", "--space", f"{VOXEL}=0.004:0.002"], "LO must be below HI"),
        (["--search", "nsga2"], "--space"),
        ([], "give one of --grid"),
        (["--grid", f"{VOXEL}=0.004", "--scenes", "moon"], "unknown scene"),
        (["--grid", f"{VOXEL}=0.004", "--recording", "/nonexistent/x.mcap"], "x.mcap"),
        (["--grid", "camera.decimation=0,2"], "camera.decimation = 0: must be in [1, 16]"),
    ],
)
def test_bad_input_exits_2_with_one_line(argv, needle, capsys, no_cluster) -> None:
    assert cli.main(["study", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err, err


def test_an_unreachable_scheduler_is_refused(capsys, tmp_path: Path) -> None:
    argv = ["study", "--grid", f"{VOXEL}=0.004", "--cache", str(tmp_path)]
    assert cli.main([*argv, "--scheduler", f"tcp://127.0.0.1:{_free_port()}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--scheduler tcp://127.0.0.1:" in err[0] and "unreachable" in err[0]
    assert not list(tmp_path.glob("*.json"))  # nothing was measured


def test_a_small_grid_on_one_local_worker(tmp_path: Path, capsys) -> None:
    out = tmp_path / "a.json"
    argv = ["study", "--grid", f"{VOXEL}=0.0035,0.007", "--scenes", "sphere_head", "--frames", "3"]
    argv += ["--workers", "1", "--cache", str(tmp_path / "cache"), "--json", str(out)]
    argv += ["--plot", str(tmp_path / "plots"), "--write-presets", str(tmp_path / "presets")]
    assert cli.main(argv) == 0
    text = capsys.readouterr().out
    assert "2 distinct trials (0 from the cache, 2 measured)" in text
    assert "3 frames per scene" in text
    data = json.loads(out.read_text())
    assert len(data["trials"]) == 2
    assert {"params", "objectives", "unsafe", "worker"} <= set(data["trials"][0])
    assert all(t["worker"].startswith("tcp://") for t in data["trials"])
    assert 1 <= len(data["front"]) <= 2 and [t for t in data["trials"] if t["default"]]
    assert (tmp_path / "plots" / "front.png").stat().st_size > 10_000
    assert (tmp_path / "plots" / "knob_perception_voxel_voxel_size_m.png").exists()
    for name in ("fast", "balanced", "accurate"):
        preset = tomllib.loads((tmp_path / "presets" / f"{name}.toml").read_text())
        assert LiveConfig.from_dict(preset).perception.voxel.voxel_size_m in (0.0035, 0.007)

    # The rerun reads every trial back: same figures, nothing measured.
    assert cli.main(argv) == 0
    assert "2 distinct trials (2 from the cache, 0 measured)" in capsys.readouterr().out
    assert json.loads(out.read_text())["trials"] == data["trials"]


def test_the_app_offers_the_shipped_presets(qtbot) -> None:
    from hapticloud.app.param_panel import ParamPanel
    from hapticloud.assets import asset_path

    panel = ParamPanel(LiveConfig())
    qtbot.addWidget(panel)
    actions = {a.text(): a for a in panel.shipped_presets.actions()}
    assert {"fast", "balanced", "accurate"} <= set(actions)
    actions["fast"].trigger()
    shipped = tomllib.loads(asset_path("presets", "fast.toml").read_text())
    assert panel.config == LiveConfig.from_dict(shipped)


def test_decimation_with_a_recording_is_refused(tmp_path: Path, capsys, no_cluster) -> None:
    from hapticloud.hardware.recording.synth import synthesize

    rec = synthesize(tmp_path / "wall.mcap", 0.5)
    argv = ["study", "--grid", "camera.decimation=1,2", "--recording", str(rec)]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "camera.decimation cannot re-render recorded frames" in err[0]


def test_a_recording_without_truth_is_scored_against_its_estimates(tmp_path: Path, capsys) -> None:
    from hapticloud.hardware.recording.synth import synthesize

    rec = synthesize(tmp_path / "wall.mcap", 1.0)
    out = tmp_path / "r.json"
    argv = ["study", "--grid", f"{VOXEL}=0.0035,0.007", "--recording", str(rec), "--frames", "4"]
    argv += ["--workers", "1", "--cache", str(tmp_path / "cache"), "--json", str(out)]
    assert cli.main(argv) == 0
    text = capsys.readouterr().out
    assert "the first 4 frames per camera of 1 recording(s) = 8 estimates per trial" in text
    assert "scored against the recorded estimates" in text
    data = json.loads(out.read_text())
    assert data["recordings"][0]["path"] == str(rec.resolve())
    assert all(t["estimates"] == 8 for t in data["trials"])
    # The synthetic recording's estimates are the exact closest points: the default agrees.
    default = next(t for t in data["trials"] if t["default"])
    assert default["objectives"]["centroid_mm_p90"] < 0.01


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "demo.mcap"
    assert cli.main(["run", "demo", "--duration", "0.5", "--quiet", "--record", str(path)]) == 0
    return path


def test_a_simulated_recording_is_scored_against_the_truth(demo_run: Path) -> None:
    from hapticloud.core.scene.loader import parse_scene
    from hapticloud.core.studies.trade.evaluate import TrialSpec, evaluate
    from hapticloud.hardware.recording.reader import Recording
    from hapticloud.hardware.study.recording import recorded_frames, recording_id, reference

    rec_id = recording_id(demo_run)
    assert "the simulator's truth (scene demo" in reference(rec_id)
    with Recording.open(demo_run) as rec:
        margins = {m.log_time_s: m.data["true_margin_m"] for m in rec.messages(["/control/state"])}
        scene = parse_scene(tomllib.loads(rec.metadata["hapticloud.scene"]["toml"]))
    r_hip = scene.config.robot.hip_radius_m
    streams = recorded_frames(rec_id, 6)
    assert streams and all(len(frames) == 6 for frames in streams.values())
    checked = 0
    for frames in streams.values():
        for f in frames:
            assert f.true_point is not None
            if f.t in margins:  # the run's own truth at the frame's tick
                checked += 1
                assert f.true_distance_m - r_hip == pytest.approx(margins[f.t], abs=1e-9)
    assert checked
    result = evaluate(TrialSpec({}, (), 6, recordings=(rec_id,)), recorded_frames=recorded_frames)
    assert result.estimates == 6 * len(streams) and result.problems == ()
    # The HIP starts 10.5 cm from the head's surface, in view: estimates close to the truth.
    assert result.objectives["centroid_mm_median"] < 2.0
