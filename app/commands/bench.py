"""``hapticloud bench STUDY``: speed/accuracy studies (each study registers below)."""

from __future__ import annotations

import argparse
import sys

from hapticloud.core.errors import ConfigError
from hapticloud.core.limits import BENCH_FRAMES_MAX, BENCH_FRAMES_MIN, MAX_DURATION_S

from . import (
    add_set_option,
    check_duration,
    check_outputs,
    overrides,
    positive_float,
    positive_int,
)

FRAMES_RANGE = f"{BENCH_FRAMES_MIN} to {BENCH_FRAMES_MAX}"


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "bench",
        help="speed/accuracy studies",
        description="Speed and accuracy studies. 'perception': accuracy against ground truth and "
        "latency per stage for the curvature-aware estimator, the paper's and a nearest-point "
        "baseline over the benchmark scenes. 'loop': the 800 Hz control tick timed in a closed "
        "loop (median, p99, deadline misses). 'gui': the desktop app's 3D view update rate and "
        "frame-to-screen latency.",
    )
    studies = parser.add_subparsers(dest="study", metavar="STUDY", required=True)
    perception = studies.add_parser(
        "perception",
        help="perception accuracy and latency",
        description="Accuracy (centroid, normal, d_proj) against the simulator's ground truth and "
        "latency per stage, side by side with the straightforward Open3D chain.",
    )
    perception.add_argument(
        "--frames",
        type=positive_int,
        default=60,
        metavar="N",
        help=f"frames per scene, {FRAMES_RANGE} (60)",
    )
    perception.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    perception.add_argument(
        "--knobs", action="store_true", help="also sweep the main knobs (speed/accuracy trade)"
    )
    add_set_option(perception, "perception.voxel.voxel_size_m=0.004")
    perception.set_defaults(handler=run_perception)
    loop = studies.add_parser(
        "loop",
        help="the 800 Hz control tick: median and p99 time, deadline misses",
        description="Times the control tick (fusion sample, robot dynamics, haptic constraints, "
        "hierarchical controller; no bus I/O) in a closed-loop simulation of a scene, cameras as "
        "oracles. A miss is a tick longer than the 1250 us period.",
    )
    loop.add_argument(
        "--duration",
        type=positive_float,
        default=15.0,
        metavar="S",
        help=f"simulated s (wall-clock with --bus), at most {MAX_DURATION_S:g} (15)",
    )
    loop.add_argument("--scene", default="impacts", help="scene file or shipped name (impacts)")
    loop.add_argument("--json", action="store_true", help="print one JSON object")
    loop.add_argument(
        "--rendered", action="store_true", help="keep the scene's rendered cameras (slower run)"
    )
    loop.add_argument(
        "--bus",
        action="store_true",
        help="run the control process in real time with drive bus I/O against the emulator "
        "(--duration is then wall-clock s)",
    )
    loop.add_argument(
        "--with-perception",
        action="store_true",
        help="with --bus: run both simulated cameras' perception in the parent at the same time",
    )
    loop.add_argument(
        "--emulator",
        choices=("process", "stepped", "thread"),
        default="process",
        help="with --bus: where the six emulated drives run: their own process on a socket-pair "
        "CAN FD bus, like real drives (default); stepped inside the tick; or a thread of the "
        "control process",
    )
    loop.add_argument(
        "--isolate-cpu",
        action="store_true",
        help="with --bus: the control process on the last CPU, perception and the drives on "
        "the others",
    )
    loop.add_argument(
        "--baseline",
        action="store_true",
        help="with --bus: then run a null loop (spins the measured median body per tick, same "
        "real-time set-up, same load) for as long: the machine's floor of misses",
    )
    add_set_option(loop, "haptics.force_enabled=false")
    loop.set_defaults(handler=run_loop)
    gui = studies.add_parser(
        "gui",
        help="the desktop app's 3D view: updates per second, render time, frame-to-screen",
        description="Updates the app's 3D view (880x500 px, two synthetic 5000-point clouds "
        "moving every frame and every overlay) at full speed and reports view updates per second "
        "(median of 1 s windows), actor-update and render time per frame, frame-to-screen latency "
        "and whether any actor was added. Starts its own Xvfb when there is no display.",
    )
    gui.add_argument(
        "--duration", type=positive_float, default=10.0, metavar="S", help="wall-clock s (10)"
    )
    gui.add_argument("--json", action="store_true", help="print one JSON object")
    gui.set_defaults(handler=run_gui)
    _register_safety(studies)
    _register_record(studies)
    _register_seek(studies)


def _register_safety(studies: argparse._SubParsersAction) -> None:
    safety = studies.add_parser(
        "safety",
        help="the shipped scenes under the degradations a clinic meets: SAFE or UNSAFE each",
        description="Runs the shipped scenes with cameras (demo, impacts, sliding) under each "
        "degradation (decimation 2/4/8/16 on one and both cameras, a camera that stops, frames "
        "delayed 50/150/400 ms, frames dropped 10/50 %%, perception slowed, the largest legal "
        "voxel), deterministic and judged on the simulator's truth, and prints a table: the "
        "smallest true margin, the share of the run held or stopped, the verdict. --hardware "
        "adds the hardware path in real time with another process holding one core. Exits 3 "
        "when a cell is UNSAFE.",
    )
    safety.add_argument(
        "--scenes",
        default="demo,impacts,sliding",
        metavar="A,B",
        help="shipped scenes with cameras, comma-separated (demo,impacts,sliding)",
    )
    safety.add_argument(
        "--only", metavar="TEXT", help="only the degradations whose name contains TEXT"
    )
    safety.add_argument(
        "--duration",
        type=positive_float,
        metavar="S",
        help="simulated s per cell (default: each scene's own)",
    )
    safety.add_argument(
        "--hardware", action="store_true", help="also the hardware path with one core busy"
    )
    safety.add_argument(
        "--workers", type=positive_int, metavar="N", help="processes (default: the cores)"
    )
    safety.add_argument("--json", metavar="PATH", help="also write every cell as JSON")
    safety.set_defaults(handler=run_safety)


def run_perception(args: argparse.Namespace) -> int:
    if not BENCH_FRAMES_MIN <= args.frames <= BENCH_FRAMES_MAX:
        raise ConfigError(f"--frames = {args.frames}: must be {FRAMES_RANGE} (frames per scene)")
    check_outputs(files={"--json": args.json})
    from hapticloud.core.studies import perception as study

    return study.main(
        frames=args.frames,
        overrides=overrides(args.set),
        json_out=args.json,
        knobs=args.knobs,
        out=sys.stdout,
    )


def run_loop(args: argparse.Namespace) -> int:
    check_duration(args.duration)
    if args.bus:
        from hapticloud.hardware.control import bench as bus_bench

        return bus_bench.main(
            args.scene,
            args.duration,
            overrides(args.set),
            args.json,
            sys.stdout,
            with_perception=args.with_perception,
            emulator=args.emulator,
            isolate_cpu=args.isolate_cpu,
            baseline=args.baseline,
        )
    from hapticloud.core.studies import loop_bench

    return loop_bench.main(
        args.scene,
        args.duration,
        overrides(args.set),
        args.json,
        sys.stdout,
        oracle=not args.rendered,
    )


def run_gui(args: argparse.Namespace) -> int:
    from hapticloud.app import bench_gui

    from .display import any_display

    return bench_gui.main(args.duration, args.json, sys.stdout, any_display())


def run_safety(args: argparse.Namespace) -> int:
    check_duration(args.duration)
    check_outputs(files={"--json": args.json})
    from hapticloud.core.studies import safety as study

    scenes = [name.strip() for name in args.scenes.split(",") if name.strip()]
    for name in scenes:
        if name not in study.SCENES:
            raise ConfigError(
                f"--scenes {name!r}: not a shipped scene with cameras ({', '.join(study.SCENES)})"
            )
    rows = [r for r in study.degradations() if not args.only or args.only in r.name]
    if not rows:
        raise ConfigError(f"--only {args.only!r}: matches no degradation")
    from hapticloud.hardware.session.safety_bench import hardware_cell, run_table

    n = len(rows) * len(scenes)
    print(f"bench safety: {len(rows)} degradations x {len(scenes)} scenes = {n} runs", flush=True)
    cells = run_table(
        scenes,
        rows,
        args.duration,
        args.workers,
        progress=lambda c: print(f"  {c['scene']:8s} {c['degradation']}: {c['line']}", flush=True),
    )
    if args.hardware:
        print("  hardware path, one core busy (impacts, 10 s in real time) ...", flush=True)
        cells.append(hardware_cell("impacts", args.duration or 10.0))
        scenes = [*scenes, *([] if "impacts" in scenes else ["impacts"])]
    print("\n".join(study.table_lines(cells, scenes)))
    if args.json:
        import json
        from pathlib import Path

        Path(args.json).write_text(json.dumps({"cells": cells}, indent=1))
    unsafe = [c for c in cells if c["verdict"] == "UNSAFE"]
    print(f"{len(cells) - len(unsafe)} of {len(cells)} runs SAFE" + (": UNSAFE:" if unsafe else ""))
    for c in unsafe:
        print(f"  {c['scene']} / {c['degradation']}: {c['line']}")
    from hapticloud.core.studies.verdict import UNSAFE_EXIT_CODE

    return UNSAFE_EXIT_CODE if unsafe else 0


def _register_record(studies: argparse._SubParsersAction) -> None:
    """``bench record``: the cost of recording a real-time session, and replay's speed."""
    record = studies.add_parser(
        "record",
        help="control misses with and without --record, the recorder's CPU, replay speed",
        description="Runs SCENE twice through the hardware layer (run --hardware), without and "
        "with recording, and replays the recording: misses per 10k ticks of each, the recorder "
        "process's share of one core, file size and rate, replay's real-time factor.",
    )
    record.add_argument("--scene", default="impacts", help="scene (impacts)")
    record.add_argument("--duration", type=positive_float, default=10.0, help="seconds (10)")
    record.add_argument("--keep", metavar="FILE.mcap", help="leave the recording here")
    record.add_argument("--json", action="store_true", help="print one JSON object")
    add_set_option(record, "cameras.decimation=2")

    def run_record(args: argparse.Namespace) -> int:
        import json

        from hapticloud.hardware.recording.bench import bench_lines, record_bench

        check_duration(args.duration)
        check_outputs(files={"--keep": args.keep})
        say = (lambda _t: None) if args.json else (lambda t: print(t, flush=True))
        result = record_bench(args.scene, args.duration, overrides(args.set), args.keep, say)
        for line in [json.dumps(result)] if args.json else bench_lines(result):
            print(line)
        return 0

    record.set_defaults(handler=run_record)


def _register_seek(studies: argparse._SubParsersAction) -> None:
    """``bench seek FILE.mcap``: a recording's open time and seek latency (headless, --gui)."""
    seek = studies.add_parser(
        "seek",
        help="a recording's open time and seek latency (the app's timeline)",
        description="Opens FILE.mcap as 'hapticloud app FILE.mcap' does (index only), reads its "
        "timeline, then seeks to random times: decode latency per seek (every camera's newest "
        "frame at or before it); with --gui also click-to-paint in the recording window.",
    )
    seek.add_argument("file", metavar="FILE.mcap", help="the recording")
    seek.add_argument("--seeks", type=positive_int, default=50, help="random seeks (50)")
    seek.add_argument("--seed", type=int, default=0, help="random seed (0)")
    seek.add_argument("--gui", action="store_true", help="also in the window (a display, or Xvfb)")
    seek.add_argument("--json", action="store_true", help="print one JSON object")

    def run_seek(args: argparse.Namespace) -> int:
        import json

        from hapticloud.hardware.recording.seek_bench import seek_bench, seek_lines

        say = (lambda _t: None) if args.json else (lambda t: print(t, flush=True))
        result = seek_bench(args.file, args.seeks, args.seed, say)
        if args.gui:
            from hapticloud.app.recording_bench import gui_seek_bench

            from .display import any_display

            with any_display():
                result["gui"] = gui_seek_bench(args.file, min(args.seeks, 30), args.seed)
                from PyQt6 import QtWidgets, sip

                app = QtWidgets.QApplication.instance()
                if app is not None:
                    sip.delete(app)
        for line in [json.dumps(result)] if args.json else seek_lines(result):
            print(line)
        return 0

    seek.set_defaults(handler=run_seek)
