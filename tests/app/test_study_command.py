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
