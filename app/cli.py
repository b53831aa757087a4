"""The ``hapticloud`` command line.

Every subcommand prints ``--help``; exit code 0 on success and 2 on bad input, with a one-line
reason on stderr. Heavy modules are imported inside the subcommands so that ``--help`` is quick.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from hapticloud.core.threads import set_environment

# Before numpy is imported anywhere: BLAS pools spinning on 2 cores cost several times the work.
set_environment(1)

from hapticloud.core.config import parse_override  # noqa: E402
from hapticloud.core.errors import HapticloudError  # noqa: E402

EXIT_BAD_INPUT = 2


def _overrides(items: Sequence[str] | None) -> dict[str, object]:
    out: dict[str, object] = {}
    for item in items or ():
        key, value = parse_override(item)
        out[key] = value
    return out


def _add_set_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--set",
        metavar="SECTION.KEY=VALUE",
        action="append",
        default=[],
        help="override one parameter (repeatable), e.g. --set perception.voxel.voxel_size_m=0.004",
    )


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def _cmd_demo(args: argparse.Namespace) -> int:
    from hapticloud.core.studies.demo import run_text_demo

    return run_text_demo(
        duration_s=args.duration,
        overrides=_overrides(args.set),
        realtime=not args.fast,
        out=sys.stdout,
    )


def _cmd_bench(args: argparse.Namespace) -> int:
    from hapticloud.core.studies import perception as study

    if args.study == "perception":
        return study.main(
            frames=args.frames,
            overrides=_overrides(args.set),
            json_out=args.json,
            knobs=args.knobs,
            out=sys.stdout,
        )
    raise HapticloudError(f"bench: unknown study {args.study!r}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hapticloud",
        description="Haptic rendering on live point clouds. With no command: the live demo.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    demo = sub.add_parser(
        "demo",
        help="headless demo: live estimates of the simulated scene against ground truth",
        description="Runs the simulated demo scene and prints each camera's estimate against "
        "the true closest point.",
    )
    demo.add_argument("--duration", type=_positive_float, default=10.0, help="seconds (10)")
    demo.add_argument("--fast", action="store_true", help="do not pace frames at 30 Hz")
    _add_set_option(demo)
    demo.set_defaults(handler=_cmd_demo)

    bench = sub.add_parser(
        "bench",
        help="speed/accuracy studies",
        description="Speed and accuracy studies. 'perception': accuracy against ground truth and "
        "latency per stage for the paper's method, the curvature-aware one and a nearest-point "
        "baseline over the benchmark scenes.",
    )
    bench.add_argument("study", choices=["perception"], help="which study")
    bench.add_argument("--frames", type=int, default=60, help="frames per scene and variant (60)")
    bench.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    bench.add_argument(
        "--knobs", action="store_true", help="also sweep the main knobs (speed/accuracy trade)"
    )
    _add_set_option(bench)
    bench.set_defaults(handler=_cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Callable[[argparse.Namespace], int] | None = getattr(args, "handler", None)
    if handler is None:
        args = parser.parse_args(["demo", *(argv or [])])
        handler = args.handler
    try:
        return handler(args)
    except HapticloudError as err:
        print(f"hapticloud: error: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
