"""``hapticloud import BAG OUT.mcap``: depth images of a ROS 1 or ROS 2 bag as a recording."""

# ruff: noqa: N999 (the module is named after its subcommand, as every one here)

from __future__ import annotations

import argparse

from . import check_outputs


def _hip(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in metres, got {text!r}") from None
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in metres, got {text!r}")
    return values


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "import",
        help="convert a ROS bag's depth images (sensor_msgs/Image + CameraInfo) to a recording",
        description="Reads a ROS 1 .bag or a ROS 2 bag (its folder, or its .db3) and writes "
        "every depth image topic (16UC1 mm or 32FC1 m) with the camera_info of its namespace "
        "as a hapticloud recording, full frames, that 'hapticloud replay' re-runs. A bag "
        "does not know the robot: the HIP is --hip, fixed, in the camera's optical frame "
        "(which becomes the world); no robot shape is excluded.",
    )
    parser.add_argument("bag", metavar="BAG", help="ROS 1 .bag, or ROS 2 bag folder / .db3")
    parser.add_argument("out", metavar="OUT.mcap", help="the recording to write")
    parser.add_argument(
        "--hip",
        type=_hip,
        required=True,
        metavar="X,Y,Z",
        help="the HIP in the camera's optical frame (m), e.g. 0,0,0.6",
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hapticloud.hardware.recording.rosbag_import import import_bag

    check_outputs(files={"OUT.mcap": args.out})
    info = import_bag(args.bag, args.out, args.hip)
    cams = ", ".join(f"{k} {v} frames" for k, v in info["cameras"].items())
    print(f"wrote {args.out}: {cams}")
    for topic, why in info["skipped"].items():
        print(f"  skipped {topic}: {why}")
    return 0
