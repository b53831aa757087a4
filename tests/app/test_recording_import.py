"""ROS bags of depth images import as recordings that replay estimates on. The bags are written
here with rosbags (a ROS 1 .bag with 16UC1 millimetres, a ROS 2 .db3 with 32FC1 metres) of a
flat wall 0.8 m in front of the camera; the HIP is 5 cm in front of it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hapticloud.app.cli import main
from hapticloud.hardware.recording.reader import Recording

W, H, F = 160, 120, 120.0
WALL_M = 0.8
HIP = "0,0,0.75"


def _messages(ts, encoding: str):
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    Image = ts.types["sensor_msgs/msg/Image"]
    Info = ts.types["sensor_msgs/msg/CameraInfo"]
    Roi = ts.types["sensor_msgs/msg/RegionOfInterest"]
    rng = np.random.default_rng(0)
    out = []
    for i in range(6):
        t_ns = 1_000_000_000 + i * 33_333_333
        stamp = Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        extra = {"seq": i} if "seq" in Header.__dataclass_fields__ else {}  # ROS 1's header
        header = Header(stamp=stamp, frame_id="cam", **extra)
        info = Info(
            header=header,
            height=H,
            width=W,
            distortion_model="plumb_bob",
            **{  # ROS 1 spells the matrices in capitals, ROS 2 in lower case
                (n if n in Info.__dataclass_fields__ else n.upper()): v
                for n, v in (
                    ("d", np.zeros(5)),
                    ("k", np.array([F, 0, (W - 1) / 2, 0, F, (H - 1) / 2, 0, 0, 1], float)),
                    ("r", np.eye(3).reshape(-1)),
                    ("p", np.zeros(12)),
                )
            },
            binning_x=0,
            binning_y=0,
            roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        )
        depth = WALL_M + rng.normal(0.0, 0.0005, (H, W))
        if encoding == "16UC1":
            data = np.round(depth * 1000).astype("<u2")
        else:
            data = depth.astype("<f4")
        image = Image(
            header=header,
            height=H,
            width=W,
            encoding=encoding,
            is_bigendian=0,
            step=W * data.itemsize,
            data=np.frombuffer(data.tobytes(), dtype=np.uint8),
        )
        out.append((t_ns, info, image))
    return out


def _write_ros1(path: Path) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    with Writer(path) as writer:
        info_c = writer.add_connection(
            "/cam/depth/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts
        )
        img_c = writer.add_connection("/cam/depth/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        for t_ns, info, image in _messages(ts, "16UC1"):
            writer.write(info_c, t_ns, ts.serialize_ros1(info, "sensor_msgs/msg/CameraInfo"))
            writer.write(img_c, t_ns + 1, ts.serialize_ros1(image, "sensor_msgs/msg/Image"))


def _write_ros2(path: Path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(path, version=8, storage_plugin=StoragePlugin.SQLITE3) as writer:
        info_c = writer.add_connection(
            "/cam/depth/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts
        )
        img_c = writer.add_connection("/cam/depth/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        for t_ns, info, image in _messages(ts, "32FC1"):
            writer.write(info_c, t_ns, ts.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
            writer.write(img_c, t_ns + 1, ts.serialize_cdr(image, "sensor_msgs/msg/Image"))


@pytest.mark.parametrize("kind", ["ros1", "ros2"])
def test_a_depth_bag_imports_and_replays_the_wall(kind: str, tmp_path: Path) -> None:
    if kind == "ros1":
        bag = tmp_path / "wall.bag"
        _write_ros1(bag)
    else:
        folder = tmp_path / "wall_ros2"
        _write_ros2(folder)
        dbs = list(folder.glob("*.db3"))
        assert dbs, "rosbags wrote no .db3"
        bag = dbs[0]  # the .db3 itself: import finds its folder
    out = tmp_path / "wall.mcap"
    assert main(["import", str(bag), str(out), "--hip", HIP]) == 0
    with Recording.open(out) as rec:
        assert rec.finished and rec.cameras == ["cam_depth"]
        frames = list(rec.frames())
        assert len(frames) == 6 and frames[0].frame.depth_m.shape == (H, W)
        assert abs(float(np.median(frames[0].frame.depth_m)) - WALL_M) < 0.002
    report = tmp_path / "replay.json"
    assert main(["replay", str(out), "--report", str(report), "--quiet"]) == 0
    data = json.loads(report.read_text())
    assert data["summary"]["frames"] == 6 and data["summary"]["with_recorded_estimate"] == 0
    valid = [f["new"] for f in data["frames"] if f["new"]["valid"]]
    assert valid, [f["new"]["reason"] for f in data["frames"]]
    for est in valid:  # the wall at z = 0.8 m, its normal towards the camera (-z)
        assert abs(est["centroid"][2] - WALL_M) < 0.003
        assert est["normal"][2] < -0.99


def test_a_bag_without_depth_images_is_one_line(tmp_path: Path, capsys) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "empty.bag"
    with Writer(bag) as writer:
        conn = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
        msg = ts.types["std_msgs/msg/String"](data="hi")
        writer.write(conn, 1, ts.serialize_ros1(msg, "std_msgs/msg/String"))
    assert main(["import", str(bag), str(tmp_path / "o.mcap"), "--hip", HIP]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hapticloud: error:") and "no sensor_msgs/Image" in err
    assert main(["import", str(tmp_path / "nope.bag"), str(tmp_path / "o.mcap"), "--hip", HIP]) == 2
