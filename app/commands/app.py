"""``hapticloud app [SCENE]``: the desktop app, live on a simulated scene (the default command)."""

from __future__ import annotations

import argparse
import dataclasses
import re
from pathlib import Path

from hapticloud.core.errors import ConfigError

from . import add_set_option, check_outputs, overrides, positive_float

DEFAULT_SIZE = (1440, 900)


def window_size(text: str) -> tuple[int, int]:
    """argparse type: ``WIDTHxHEIGHT`` in pixels."""
    match = re.fullmatch(r"(\d+)x(\d+)", text.strip())
    if not match:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 1280x800, got {text!r}")
    w, h = int(match[1]), int(match[2])
    if not (640 <= w <= 7680 and 480 <= h <= 4320):
        raise argparse.ArgumentTypeError(f"{text}: must be between 640x480 and 7680x4320")
    return w, h


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "app",
        help="the desktop app: live 3D view, parameters, plots (default command)",
        description="Opens the main window on a simulated scene running live: the perception "
        "pipeline's clouds, shells and estimates in 3D, the generated parameter panel, live "
        "plots and the emergency stop (Esc or Space).",
    )
    parser.add_argument(
        "scene",
        nargs="?",
        default="demo",
        help="built-in scene (default: demo, the seated patient reaching to the face), a shipped "
        "scene of assets/scenes (impacts, sliding, wall, moving-surface) or a scene file; or a "
        "recording (FILE.mcap) to play with its timeline",
    )
    parser.add_argument(
        "--screenshot", metavar="PATH", help="save the window as PNG after --exit-after seconds"
    )
    parser.add_argument(
        "--report",
        metavar="PATH",
        help="write what the window showed as JSON at exit: session states and faults, camera "
        "rates, real-time factor, fused error against the truth, view fps, frame-to-screen "
        "latency and the run's verdict (SAFE/UNSAFE)",
    )
    parser.add_argument(
        "--exit-after",
        metavar="S",
        type=positive_float,
        help="quit after S seconds (default 3 with --screenshot)",
    )
    parser.add_argument(
        "--size",
        metavar="WxH",
        type=window_size,
        default=DEFAULT_SIZE,
        help="window size in pixels (default {}x{})".format(*DEFAULT_SIZE),
    )
    parser.add_argument(
        "--render-scale",
        metavar="S",
        type=render_scale,
        default=None,
        help="3D view render resolution per screen pixel, 0.25-1 (default auto: 0.75 under "
        "software OpenGL, where shading is most of the GUI's CPU; 1 with a GPU)",
    )
    parser.add_argument("--preset", metavar="FILE", help="start with this parameter preset (TOML)")
    parser.add_argument(
        "--view",
        choices=("follow", "overview", "front", "side"),
        default="follow",
        help="3D camera preset (default: follow, the HIP as it moves)",
    )
    parser.add_argument(
        "--color-by",
        choices=("camera", "stage"),
        default="camera",
        help="colour the points by camera or by pipeline stage (default: camera)",
    )
    add_set_option(parser, "perception.voxel.voxel_size_m=0.004")
    parser.add_argument(
        "--decimation",
        type=int,
        choices=(1, 2, 4),
        default=2,
        help="divide the simulated cameras' resolution (2, the scenes' default: 424x240, the "
        "D435's decimation filter, at rate on 2 cores; 1: 848x480 as the paper)",
    )
    parser.add_argument(
        "--speed", type=positive_float, default=1.0, help="simulation time per wall time (1)"
    )
    parser.add_argument(
        "--no-session",
        action="store_true",
        help="perception only: do not start the 800 Hz control process with its emulated drives",
    )
    parser.add_argument(
        "--enable",
        action="store_true",
        help="enable the session (torque on) as the Enable button does, as soon as it is ready "
        "and sees: READY, the space around the HIP known and every watchdog quiet",
    )
    from .app_recording import add_recording_options

    add_recording_options(parser)
    parser.set_defaults(handler=run)


#: ``nice`` value the live window's process takes before it builds the window (so its render
#: threads inherit it): on a machine short of cores the display gives way to the perception
#: worker (SCHED_FIFO ``WORKER_FIFO_PRIORITY``, or nice ``WORKER_NICE`` where refused) whose
#: frames the control loop's watchdogs wait for; the control loop runs SCHED_FIFO above both (or
#: nice ``FALLBACK_NICE``). Only for root: the processes the window starts inherit its value,
#: and without privilege they could not set theirs back. A process already nicer keeps its value.
GUI_NICE = 5


def _give_way() -> None:
    import os

    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return
    try:
        os.setpriority(os.PRIO_PROCESS, 0, max(os.getpriority(os.PRIO_PROCESS, 0), GUI_NICE))
    except OSError:
        pass  # refused: the default priority


def render_scale(text: str) -> float | None:
    """argparse type: ``auto`` (None) or a number in [0.25, 1]."""
    if text == "auto":
        return None
    value = positive_float(text)
    if not 0.25 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be auto or in [0.25, 1], got {text}")
    return value


def run(args: argparse.Namespace) -> int:
    from hapticloud.app.recording_source import is_recording
    from hapticloud.hardware.live.contract import LiveConfig
    from hapticloud.hardware.live.scenes import SimSettings, scene_spec

    if is_recording(args.scene):
        from .app_recording import run_recording

        return run_recording(args)
    check_outputs(files={"--record": args.record})
    check_outputs(files={"--screenshot": args.screenshot, "--report": args.report})
    # A one-line error for an unknown scene, a bad file or one the app cannot show, before any
    # process starts (the build is cached: the window reuses it).
    scene_spec(args.scene).build(decimation=args.decimation)
    if args.preset:
        config = LiveConfig.load(args.preset)
    elif args.no_session:
        config = LiveConfig()
    else:
        from hapticloud.hardware.live.session import scene_tables

        config = dataclasses.replace(LiveConfig(), **scene_tables(args.scene))
    try:
        config = config.with_overrides(overrides(args.set))
    except ConfigError as err:
        raise ConfigError(f"--set {err}") from None
    # Perception alone has no arm to move the HIP: the demo then follows its scripted reach.
    scene = "demo-path" if args.no_session and args.scene == "demo" else args.scene
    settings = SimSettings(scene=scene, speed=args.speed, decimation=args.decimation)
    from .display import window_display

    display, exit_after, shot = window_display(args.screenshot, args.exit_after)
    with display:
        return _run_window(settings, config, args, exit_after, shot)


def _run_window(
    settings: object,
    config: object,
    args: argparse.Namespace,
    exit_after: float | None,
    shot: Path | None,
) -> int:
    from hapticloud.app.commands.display import desktop_application
    from hapticloud.app.main_window import MainWindow
    from hapticloud.app.scene_view import SceneView
    from hapticloud.app.screenshot import run_window
    from hapticloud.hardware.live.session import Session
    from hapticloud.hardware.live.source import LiveSource

    _give_way()
    app = desktop_application()
    SceneView.default_render_scale = args.render_scale
    scene = settings.scene  # type: ignore[attr-defined]
    window = MainWindow(
        lambda cfg, session=None: LiveSource(settings, cfg, session=session),  # type: ignore[arg-type]
        config,  # type: ignore[arg-type]
        title=scene,
        make_session=(
            None if args.no_session else (lambda: Session(scene, enable_when_ready=args.enable))
        ),
    )
    from hapticloud.app.record_controls import install_record_controls

    install_record_controls(window, args.record)
    if args.report:
        from hapticloud.app.report import AppReport

        window.report = AppReport(window.source.geometry.r_hip_m if window.source else 0.04)
    window.controls.color_mode.setCurrentText(args.color_by)
    window.controls.preset_actions[args.view].trigger()
    window.resize(*args.size)
    window.show()

    def report() -> None:
        if window.report is not None:
            print(f"report: {window.report.write(args.report)}", flush=True)
            print(window.report.to_json()["truth"]["line"], flush=True)

    return run_window(app, window, shot, exit_after, before_close=report)
