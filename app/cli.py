"""The ``hapticloud`` command line.

Every subcommand prints ``--help``; exit code 0 on success and 2 on bad input, with a one-line
reason on stderr. Subcommands live in :mod:`hapticloud.app.commands`, one module each.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable, Sequence

from hapticloud.core.threads import set_environment

# Before numpy is imported anywhere: BLAS pools spinning on 2 cores cost several times the work.
set_environment(1)

from hapticloud.core.errors import HapticloudError  # noqa: E402

EXIT_BAD_INPUT = 2
# Registration order is the order --help lists them.
COMMANDS = ("app", "demo", "run", "bench")
DEFAULT_COMMAND = ["app"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hapticloud",
        description="Haptic rendering on live point clouds. With no command: the desktop app "
        "on the simulated demo scene ('hapticloud demo' prints the demo as text).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"hapticloud.app.commands.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    # `hapticloud [app] [SCENE] [options]`: anything that is not a command (or a request for the
    # top-level help) goes to the default command.
    if not argv or (argv[0] not in COMMANDS and argv[0] not in ("-h", "--help")):
        argv = DEFAULT_COMMAND + argv
    args = parser.parse_args(argv)
    handler: Callable[[argparse.Namespace], int] | None = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return EXIT_BAD_INPUT
    try:
        return handler(args)
    except HapticloudError as err:
        print(f"hapticloud: error: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
