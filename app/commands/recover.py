"""``hapticloud recover FILE OUT``: an unfinished recording rewritten complete and indexed."""

from __future__ import annotations

import argparse

from . import check_outputs


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "recover",
        help="rewrite an unfinished recording (killed, disk full) complete and indexed",
        description="Copies every message of FILE's whole chunks (everything up to about one "
        "flush period, 0.5 s, before the recording stopped) into OUT, finishes OUT with its "
        "index and opens it again to check that it holds them all.",
    )
    parser.add_argument("file", metavar="FILE", help="the unfinished .mcap recording")
    parser.add_argument("out", metavar="OUT", help="the recovered .mcap to write")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hapticloud.hardware.recording.recover import recover

    check_outputs(files={"OUT": args.out})
    info = recover(args.file, args.out)
    was = "finished already" if info["was_finished"] else f"unfinished ({info['truncation']})"
    print(
        f"{args.file}: {was}; wrote {args.out}: {info['messages']} messages, "
        f"{info['start_s']:.3f} s to {info['end_s']:.3f} s, {info['bytes'] / 1e6:.1f} MB, "
        "indexed and checked"
    )
    return 0
