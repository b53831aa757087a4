"""``hapticloud app FILE.mcap``: the recording's window, and the app's recording options.

Not a subcommand of its own: ``app`` hands a positional argument that names a recording (a
``.mcap`` name or the MCAP magic, :func:`~hapticloud.app.recording_source.is_recording`) here.
A file that is not a readable recording is one line and exit 2, before any window.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from hapticloud.core.errors import ConfigError

from . import check_outputs, overrides


def add_recording_options(parser: argparse.ArgumentParser) -> None:
    """``--record`` (live sessions) and ``--at`` / ``--play`` (recordings) on ``app``."""
    parser.add_argument(
        "--record",
        metavar="FILE.mcap",
        help="record the session from the start (camera frames, estimates, control states, "
        "events), as the Record button does; not with a recording",
    )
    parser.add_argument(
        "--at",
        metavar="S",
        type=float,
        help="with a recording: put the cursor S seconds after its start",
    )
    parser.add_argument(
        "--play", action="store_true", help="with a recording: play it from the start (or --at)"
    )
    parser.add_argument(
        "--rerun",
        action="store_true",
        help="with a recording: re-run it at once with the recorded parameters changed by "
        "--preset and --set, as the Re-run button does",
    )


def recording_config(player: Any, args: argparse.Namespace) -> Any:
    """The panel's parameters: the recording's own, then ``--preset``'s perception and fusion,
    then ``--set``."""
    from hapticloud.app.recording_source import recorded_live_config
    from hapticloud.hardware.live.contract import LiveConfig

    config = recorded_live_config(player)
    if args.preset:
        preset = LiveConfig.load(args.preset)
        config = dataclasses.replace(config, perception=preset.perception, fusion=preset.fusion)
    try:
        return config.with_overrides(overrides(args.set))
    except ConfigError as err:
        raise ConfigError(f"--set {err}") from None


def run_recording(args: argparse.Namespace) -> int:
    """Open ``args.scene`` as a recording and show it (see the module docstring)."""
    from hapticloud.app.recording_source import RecordingSource
    from hapticloud.hardware.recording.cursor import RecordingPlayer

    if args.record:
        raise ConfigError(f"--record: {args.scene} is a recording; record a live session")
    if args.report:
        raise ConfigError("--report: reports a live session; not with a recording")
    check_outputs(files={"--screenshot": args.screenshot})
    player = RecordingPlayer(args.scene)  # RecordingError: one line, exit 2
    try:
        source = RecordingSource(player, recording_config(player, args))
        if args.at is not None:
            player.seek(player.start_s + args.at)
        if args.speed != 1.0:
            player.set_speed(args.speed)
        from .display import window_display

        display, exit_after, shot = window_display(args.screenshot, args.exit_after)
    except BaseException:
        player.close()
        raise
    with display:
        return _window(source, args, exit_after, shot)


def _window(
    source: Any, args: argparse.Namespace, exit_after: float | None, shot: Path | None
) -> int:
    from hapticloud.app.commands.display import desktop_application
    from hapticloud.app.recording_window import RecordingWindow
    from hapticloud.app.scene_view import SceneView
    from hapticloud.app.screenshot import run_window

    app = desktop_application()
    SceneView.default_render_scale = args.render_scale
    window = RecordingWindow(source)
    window.controls.color_mode.setCurrentText(args.color_by)
    window.controls.preset_actions[args.view].trigger()
    window.resize(*args.size)
    window.show()
    if args.play:
        source.player.play()
    if args.rerun:
        window.start_rerun()
    return run_window(app, window, shot, exit_after)


__all__ = ["add_recording_options", "recording_config", "run_recording"]
