"""Recordings of the deterministic run: the same results with and without --record, a plain MCAP
reader reads every channel, and replay with the recording's parameters reproduces it exactly."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hapticloud.app.cli import main
from hapticloud.core.geometry import Box, Capsule, Sphere
from hapticloud.core.perception import SurfaceEstimate
from hapticloud.core.recording import primitive_from_dict, primitive_to_dict
from hapticloud.hardware.control.messages import (
    estimate_from_dict,
    estimate_from_wire,
    estimate_to_dict,
    estimate_to_wire,
)
from hapticloud.hardware.recording import format as fmt
from hapticloud.hardware.recording.reader import Recording

DURATION = "1.5"


def _without_timings(data: object) -> object:
    """The report without wall-clock figures (they differ between any two runs)."""
    noisy = ("wall", "_us", "_ms", "timing", "real_time", "misses")  # wall-clock figures
    if isinstance(data, dict):
        return {k: _without_timings(v) for k, v in data.items() if not any(n in k for n in noisy)}
    if isinstance(data, list):
        return [_without_timings(v) for v in data]
    return data


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("rec")
    paths = {
        "mcap": out / "sliding.mcap",
        "with": out / "with.json",
        "without": out / "without.json",
    }
    base = ["run", "sliding", "--duration", DURATION, "--quiet"]
    assert main([*base, "--report", str(paths["with"]), "--record", str(paths["mcap"])]) == 0
    assert main([*base, "--report", str(paths["without"])]) == 0
    return paths


def test_recording_does_not_change_the_run(recorded: dict[str, Path]) -> None:
    with_rec = json.loads(recorded["with"].read_text())
    without = json.loads(recorded["without"].read_text())
    assert with_rec["truth"]["min_margin_m"] is not None
    assert _without_timings(with_rec) == _without_timings(without)


def test_a_plain_mcap_reader_reads_every_channel(recorded: dict[str, Path]) -> None:
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    with open(recorded["mcap"], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["hapticloud"]["format_version"] == str(fmt.FORMAT_VERSION)
        assert "voxel" in meta["hapticloud.config"]["perception"]
        seen: dict[str, object] = {}
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "json":
                body = json.loads(message.data)
            else:
                body = DecoderFactory().decoder_for(channel.message_encoding, schema)(message.data)
            seen.setdefault(channel.topic, (schema.name, body))
    topics = set(seen)
    for cam in ("front", "right45"):
        for topic in (
            fmt.depth_topic(cam),
            fmt.calibration_topic(cam),
            fmt.capture_topic(cam),
            fmt.estimate_topic(cam),
        ):
            assert topic in topics
    assert {fmt.TF_TOPIC, fmt.CONTROL_TOPIC, fmt.SURFACE_TOPIC} <= topics
    name, image = seen[fmt.depth_topic("front")]
    assert name == "foxglove.RawImage" and image.encoding == "32FC1"
    assert image.step == 4 * image.width and len(image.data) == image.step * image.height
    name, calib = seen[fmt.calibration_topic("front")]
    assert (calib.width, calib.height) == (image.width, image.height)
    name, est = seen[fmt.estimate_topic("front")]
    assert name == "hapticloud.SurfaceEstimate"
    assert set(est) == {
        "t", "camera", "centroid", "normal", "valid", "quality", "reason", "method", "seq",
        "free_m", "hip", "residual_m",
    }  # fmt: skip


def test_replay_with_the_recorded_parameters_reproduces_every_estimate(
    recorded: dict[str, Path], tmp_path: Path
) -> None:
    report = tmp_path / "replay.json"
    assert main(["replay", str(recorded["mcap"]), "--report", str(report), "--quiet"]) == 0
    summary = json.loads(report.read_text())["summary"]
    assert summary["frames"] == summary["with_recorded_estimate"] > 60
    assert summary["identical"] == summary["frames"]
    assert summary["both_valid"] > 10
    assert summary["max_centroid_diff_mm"] == 0.0
    assert summary["max_fused_diff_mm"] == 0.0
    assert summary["roi_exceeded"] == 0


def test_replay_with_other_parameters_differs_and_says_where_it_saw_less(
    recorded: dict[str, Path], tmp_path: Path
) -> None:
    report = tmp_path / "replay.json"
    argv = ["replay", str(recorded["mcap"]), "--report", str(report), "--quiet"]
    assert main([*argv, "--set", "perception.voxel.voxel_size_m=0.006"]) == 0
    summary = json.loads(report.read_text())["summary"]
    assert summary["identical"] < summary["frames"]
    assert summary["max_centroid_diff_mm"] > 0.0 and summary["roi_exceeded"] == 0
    # A larger workspace needs pixels an ROI recording did not keep: counted, not hidden.
    assert main([*argv, "--set", "perception.crop.workspace_radius_m=0.25"]) == 0
    assert json.loads(report.read_text())["summary"]["roi_exceeded"] > 0


def test_reader_seeks_and_reads_a_time_range(recorded: dict[str, Path]) -> None:
    with Recording.open(recorded["mcap"]) as rec:
        assert rec.finished and rec.cameras == ["front", "right45"]
        assert rec.end_s == pytest.approx(1.5, abs=0.02)
        window = list(rec.messages([fmt.CONTROL_TOPIC], 0.5, 1.0))
        assert len(window) == 400  # every tick of 800 Hz for 0.5 s
        assert all(0.5 <= m.log_time_s < 1.0 for m in window)
        assert window == sorted(window, key=lambda m: m.log_time_s)
        now = rec.seek(1.0)
        assert now[fmt.CONTROL_TOPIC].log_time_s <= 1.0
        assert now[fmt.depth_topic("front")].log_time_s > 1.0 - 1 / 30 - 1e-9
        frames = list(rec.frames(["front"], 0.0, 0.2))
        assert [f.camera for f in frames] == ["front"] * len(frames) and len(frames) == 6
        assert all(f.exclude and isinstance(f.exclude[0], Capsule) for f in frames)


def test_the_estimate_dict_is_the_wire_form_named() -> None:
    est = SurfaceEstimate(
        0.25, "front", [0.1, 0.2, 0.3], [0.0, 0.6, 0.8], True, quality=0.7, seq=4,
        hip=[0.1, 0.2, 0.4], method="quadric",
    )  # fmt: skip
    data = json.loads(json.dumps(estimate_to_dict(est)))
    back, wire = estimate_from_dict(data), estimate_from_wire(estimate_to_wire(est))
    for a in (back, wire):
        assert a.t == est.t and a.seq == 4 and a.valid and a.method == "quadric"
        assert np.array_equal(a.centroid, est.centroid) and np.array_equal(a.normal, est.normal)
        assert np.array_equal(a.hip, est.hip)


def test_exclusion_shapes_round_trip_exactly() -> None:
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    shapes = [
        Capsule([0.1, 0.2, 1 / 3], [0.4, 0.5, 0.6], 0.03),
        Sphere([0.0, 0.1, 0.2], 0.04),
        Box([0.1, 0.1, 0.1], [0.2, 0.3, 0.4], rot),
    ]
    for shape in shapes:
        back = primitive_from_dict(json.loads(json.dumps(primitive_to_dict(shape))))
        assert type(back) is type(shape)
        for name in shape.__dataclass_fields__:
            assert np.array_equal(getattr(back, name), getattr(shape, name))
