"""One module per ``hapticloud`` subcommand; each exposes ``register(subparsers)``.

A subcommand's handler takes the parsed ``argparse.Namespace`` and returns the exit code; it
imports its heavy modules inside the handler, so ``hapticloud --help`` stays quick.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from hapticloud.core.config import parse_override


def overrides(items: Sequence[str] | None) -> dict[str, object]:
    """``--set key=value`` items as an ordered ``{key: value}`` dict (values parsed as TOML)."""
    out: dict[str, object] = {}
    for item in items or ():
        key, value = parse_override(item)
        out[key] = value
    return out


def add_set_option(parser: argparse.ArgumentParser, example: str) -> None:
    parser.add_argument(
        "--set",
        metavar="SECTION.KEY=VALUE",
        action="append",
        default=[],
        help=f"override one parameter (repeatable), e.g. --set {example}",
    )


def positive_float(text: str) -> float:
    """argparse type: a positive number (a clear message otherwise, exit code 2)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def positive_int(text: str) -> int:
    """argparse type: a positive integer."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text}")
    return value
