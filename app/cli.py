"""The ``hapticloud`` command line.

Every subcommand prints ``--help``; exit code 0 on success and 2 on bad input, with a one-line
reason on stderr. Subcommands live in :mod:`hapticloud.app.commands`, one module each.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from hapticloud.core.threads import set_environment

# Before numpy is imported anywhere: BLAS pools spinning on 2 cores cost several times the work.
set_environment(1)

from hapticloud.app.commands import reason  # noqa: E402
from hapticloud.app.commands.version import VersionAction  # noqa: E402
from hapticloud.core.errors import ConfigError, HapticloudError  # noqa: E402

EXIT_BAD_INPUT = 2
# Registration order is the order --help lists them.
COMMANDS = (
    "app",
    "demo",
    "run",
    "replay",
    "info",
    "recover",
    "import",
    "bench",
    "study",
    "install-desktop",
)
DEFAULT_COMMAND = ["app"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hapticloud",
        description="Haptic rendering on live point clouds. With no command: the desktop app "
        "on the simulated demo scene ('hapticloud demo' prints the demo as text).",
    )
    parser.add_argument("--version", action=VersionAction)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"hapticloud.app.commands.{name.replace('-', '_')}").register(sub)
    return parser


def route(argv: Sequence[str]) -> list[str]:
    """The arguments to parse: ``hapticloud [app] [SCENE] [options]``.

    Anything that is not a command (or a request for the top-level help) goes to the default
    command, except a first word that is neither a file nor a shipped scene but close to a
    command's name: a mistyped command (:class:`ConfigError` saying which it resembles).
    """
    argv = list(argv)
    if argv and argv[0] in (*COMMANDS, "-h", "--help", "--version"):
        return argv
    if argv and not argv[0].startswith("-"):
        _refuse_mistyped_command(argv[0])
    return DEFAULT_COMMAND + argv


def _refuse_mistyped_command(word: str) -> None:
    close = difflib.get_close_matches(word, COMMANDS, n=1)
    if not close or Path(word).exists():
        return
    from hapticloud.core.scene import resolve_scene

    if not resolve_scene(word).exists():
        raise ConfigError(f"unknown command {word!r} (did you mean {close[0]!r}?)")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(route(sys.argv[1:] if argv is None else argv))
        handler: Callable[[argparse.Namespace], int] | None = getattr(args, "handler", None)
        if handler is None:
            parser.print_help()
            return EXIT_BAD_INPUT
        return handler(args)
    except HapticloudError as err:
        print(f"hapticloud: error: {reason(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
