"""``hapticloud demo``: the headless demo, estimates against ground truth as text."""

from __future__ import annotations

import argparse
import sys

from . import add_set_option, check_outputs, overrides, positive_float


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "demo",
        help="headless demo: live estimates of the simulated scene against ground truth",
        description="Runs the simulated demo scene (two D435s, the patient reaching to the face) "
        "and prints each camera's estimate against the true closest point.",
    )
    parser.add_argument("--duration", type=positive_float, default=10.0, help="seconds (10)")
    parser.add_argument("--fast", action="store_true", help="do not pace frames at 30 Hz")
    parser.add_argument(
        "--record", metavar="FILE.mcap", help="record the frames and estimates to this MCAP file"
    )
    add_set_option(parser, "perception.voxel.voxel_size_m=0.004")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hapticloud.app.text_demo import run_text_demo

    check_outputs(files={"--record": args.record})
    return run_text_demo(
        duration_s=args.duration,
        overrides=overrides(args.set),
        realtime=not args.fast,
        out=sys.stdout,
        record=args.record,
    )
