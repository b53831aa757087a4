"""``hapticloud bench STUDY``: speed/accuracy studies (each study registers below)."""

from __future__ import annotations

import argparse
import sys

from hapticloud.core.errors import ConfigError

from . import add_set_option, overrides, positive_int


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "bench",
        help="speed/accuracy studies",
        description="Speed and accuracy studies. 'perception': accuracy against ground truth and "
        "latency per stage for the curvature-aware estimator, the paper's and a nearest-point "
        "baseline over the benchmark scenes.",
    )
    studies = parser.add_subparsers(dest="study", metavar="STUDY", required=True)
    perception = studies.add_parser(
        "perception",
        help="perception accuracy and latency",
        description="Accuracy (centroid, normal, d_proj) against the simulator's ground truth and "
        "latency per stage, side by side with the straightforward Open3D chain.",
    )
    perception.add_argument("--frames", type=positive_int, default=60, help="frames per scene (60)")
    perception.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    perception.add_argument(
        "--knobs", action="store_true", help="also sweep the main knobs (speed/accuracy trade)"
    )
    add_set_option(perception, "perception.voxel.voxel_size_m=0.004")
    perception.set_defaults(handler=run_perception)


def run_perception(args: argparse.Namespace) -> int:
    from hapticloud.core.studies import perception as study

    if args.frames < study.SEGMENT_FRAMES:
        raise ConfigError(f"--frames = {args.frames}: must be at least {study.SEGMENT_FRAMES}")
    return study.main(
        frames=args.frames,
        overrides=overrides(args.set),
        json_out=args.json,
        knobs=args.knobs,
        out=sys.stdout,
    )
