"""One module per ``hapticloud`` subcommand; each exposes ``register(subparsers)``.

A subcommand's handler takes the parsed ``argparse.Namespace`` and returns the exit code; it
imports its heavy modules inside the handler, so ``hapticloud --help`` stays quick.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from hapticloud.core.config import parse_override
from hapticloud.core.errors import ConfigError
from hapticloud.core.limits import MAX_DURATION_S


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


def check_duration(seconds: float | None) -> None:
    """``--duration``: at most a scene's longest run (``hapticloud.core.limits.MAX_DURATION_S``)."""
    if seconds is not None and seconds > MAX_DURATION_S:
        raise ConfigError(
            f"--duration = {seconds:g}: must be at most {MAX_DURATION_S:g} s "
            "(the longest scene run, as scene.duration_s)"
        )


def check_outputs(
    files: Mapping[str, str | None] | None = None,
    folders: Mapping[str, str | None] | None = None,
) -> None:
    """Refuse, before a run starts, an output it could not write at its end (one-line ConfigError).

    ``files`` maps an option to the file it writes: not a folder, in a folder that exists or can be
    made, writable. ``folders`` maps an option to the folder it writes into: a folder, or a path
    that can be made one. A ``None`` path (the option not given) passes.
    """
    for option, path in (files or {}).items():
        if path is not None:
            _check_output(f"{option} {path}", Path(path), folder=False)
    for option, path in (folders or {}).items():
        if path is not None:
            _check_output(f"{option} {path}", Path(path), folder=True)


def _check_output(where: str, path: Path, *, folder: bool) -> None:
    if path.is_dir() and not folder:
        raise ConfigError(f"{where}: is a folder, expected a file")
    if path.exists() and not path.is_dir() and folder:
        raise ConfigError(f"{where}: is a file, expected a folder")
    target = path if path.exists() else _nearest_existing(where, path)
    if not os.access(target, os.W_OK | (os.X_OK if target.is_dir() else 0)):
        what = "not writable" if target == path else f"folder {target} is not writable"
        raise ConfigError(f"{where}: {what}")


def _nearest_existing(where: str, path: Path) -> Path:
    """The closest existing ancestor of ``path`` (where its missing folders would be made)."""
    for parent in path.parents:  # ends with "." or "/"
        if parent.exists():
            if not parent.is_dir():
                raise ConfigError(f"{where}: {parent} is a file, not a folder")
            return parent
    raise ConfigError(f"{where}: no existing folder above it")  # pragma: no cover


def reason(err: BaseException) -> str:
    """One non-empty line saying why ``err`` happened.

    Its first line; when that is a header ending in ':' over more (a child's traceback), the last
    line below it too; the exception type's name where the text says nothing.
    """
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    if not lines:
        return type(err).__name__
    if lines[0].endswith(":"):
        return f"{lines[0]} {lines[-1] if len(lines) > 1 else type(err).__name__}"
    return lines[0]
