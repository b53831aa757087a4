"""``hapticloud run SCENE``: a headless closed-loop session in simulation, report and figures."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from hapticloud.core.limits import MAX_DURATION_S

from . import (
    add_set_option,
    check_duration,
    check_outputs,
    overrides,
    positive_float,
    reason,
)


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "run",
        help="headless closed-loop run of a scene: JSON report and the paper's figures",
        description="Runs SCENE (a scene file, or the name of a shipped one: impacts, sliding, "
        "wall, moving-surface, demo) in simulated time: cameras, perception, fusion, the 800 Hz "
        "tick and the exoskeleton's dynamics with the patient's arm. Prints a summary; --report "
        "writes the JSON report, --plot the figures (Fig. 8, Fig. 11; Fig. 12 with --sweep).",
    )
    parser.add_argument("scene", metavar="SCENE", help="scene file or shipped scene name")
    parser.add_argument(
        "--duration",
        type=positive_float,
        metavar="S",
        help=f"simulated seconds, at most {MAX_DURATION_S:g} (default: the scene's duration_s)",
    )
    parser.add_argument("--report", metavar="PATH", help="write the JSON report here")
    parser.add_argument("--plot", metavar="DIR", help="write the figures (PNG) into this folder")
    parser.add_argument(
        "--sweep",
        metavar="KEY=V1,V2,...",
        help="run once per value of one parameter, e.g. surface.speed_mps=0.5,1,1.5,2 "
        "(Fig. 12 plots the margin against it)",
    )
    parser.add_argument(
        "--compare-paper",
        action="store_true",
        help="only with --sweep (refused alone): also run each value with the paper's "
        "formulation (no surface-velocity feed-forward); for one run, sweep one value, e.g. "
        "--sweep surface.speed_mps=1.0",
    )
    parser.add_argument(
        "--hardware",
        action="store_true",
        help="run the session in real time through the hardware layer: the 800 Hz control "
        "process against six emulated CAN FD drives moving the scene's exoskeleton and patient, "
        "perception outside the loop (not with --sweep or --plot)",
    )
    parser.add_argument(
        "--record",
        metavar="FILE.mcap",
        help="record the run (camera frames, estimates, the tick's state, events) to this MCAP "
        "file; 'hapticloud info' and 'hapticloud replay' read it, Foxglove opens it "
        "(not with --sweep)",
    )
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_set_option(parser, "surface.speed_mps=2.0")
    parser.set_defaults(handler=run)


def _write_json(path: str, data: Any) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(data, indent=2))


def run(args: argparse.Namespace) -> int:
    from hapticloud.core.errors import ConfigError
    from hapticloud.core.scene import load_scene
    from hapticloud.core.sim.closed_loop import InfeasibleSceneError
    from hapticloud.core.studies import run as study

    say = (lambda *_: None) if args.quiet else (lambda line: print(line, flush=True))
    # Every argument is checked before the run: a long run is never thrown away at its end.
    check_duration(args.duration)
    if args.compare_paper and not args.sweep:
        raise ConfigError("--compare-paper: needs --sweep (for one run: --sweep KEY=VALUE)")
    if args.hardware and (args.sweep or args.plot):
        raise ConfigError("--hardware: not with --sweep or --plot")
    if args.record and args.sweep:
        raise ConfigError("--record: not with --sweep (one recording per run)")
    check_outputs(
        files={"--report": args.report, "--record": args.record}, folders={"--plot": args.plot}
    )
    scene = load_scene(args.scene, overrides(args.set))
    if args.hardware:
        return _run_hardware(args, scene, say)
    try:
        if args.sweep:
            key, values = study.parse_sweep(args.sweep)
            runs = study.sweep(
                scene,
                key,
                values,
                compare_paper=args.compare_paper,
                duration_s=args.duration,
                progress=lambda text: say(f"running {scene.name} with {text} ..."),
            )
            rep = study.sweep_report(key, runs)
            for row in rep["rows"]:
                m = row["min_margin_m"]
                say(
                    f"{key} = {row['value']} ({row['formulation']}): min margin "
                    f"{'n/a' if m is None else f'{m * 1e3:+.1f} mm'}, "
                    f"wall time {row['wall_time_s']:.1f} s, {row['verdict']}"
                )
            if args.report:
                _write_json(args.report, rep)
            if args.plot:
                from hapticloud.app import plots

                out = Path(args.plot)
                say(f"wrote {plots.fig12_speed_sweep(key, runs, rep['rows'], out / 'fig12.png')}")
                first = runs[0]["record"]
                _plot_single(first, out, say, suffix=f"_{key.split('.')[-1]}_{runs[0]['value']}")
            # The paper's formulation is there to be compared, not run: only ours decides.
            ours = [r for r in rep["rows"] if r["formulation"] == "ours"]
            return _verdict_exit(
                args, [r["verdict_line"] for r in ours], [r["verdict"] for r in ours]
            )
        record = _run_recorded(args, scene, say) if args.record else None
        if record is None:
            record = study.run_scene(scene, None, args.duration)
    except InfeasibleSceneError as err:
        return _infeasible(args, scene, err)
    rep = study.report(record)
    for line in study.summary_lines(rep):
        say(line)
    if args.report:
        _write_json(args.report, rep)
        say(f"wrote {args.report}")
    if args.plot:
        _plot_single(record, Path(args.plot), say)
    return _verdict_exit(args, [rep["truth"]["line"]], [rep["verdict"]])


def _verdict_exit(args: argparse.Namespace, lines: list[str], verdicts: list[str]) -> int:
    """Exit code 3 (documented) when a run was UNSAFE; its line goes to stderr under --quiet."""
    from hapticloud.core.studies.verdict import UNSAFE_EXIT_CODE

    unsafe = [line for line, v in zip(lines, verdicts, strict=True) if v == "UNSAFE"]
    if not unsafe:
        return 0
    if args.quiet:
        for line in unsafe:
            print(line, file=sys.stderr)
    return UNSAFE_EXIT_CODE


def _infeasible(args: argparse.Namespace, scene: Any, err: Exception) -> int:
    """Reported, not crashed: the report says why, the exit code says bad input."""
    if args.report:
        _write_json(
            args.report, {"scene": {"path": scene.path}, "feasible": False, "reason": str(err)}
        )
    print(f"hapticloud: error: scene is infeasible: {err}", file=sys.stderr)
    return 2


def _run_hardware(args: argparse.Namespace, scene: Any, say: Any) -> int:
    from hapticloud.core.sim.closed_loop import InfeasibleSceneError
    from hapticloud.hardware.session.run import run_session, summary_lines

    try:
        rep = run_session(
            args.scene, overrides(args.set), args.duration, progress=say, record=args.record
        )
    except InfeasibleSceneError as err:
        return _infeasible(args, scene, err)
    except (RuntimeError, TimeoutError) as err:
        print(f"hapticloud: error: {reason(err)}", file=sys.stderr)
        return 1
    for line in summary_lines(rep):
        say(line)
    if args.report:
        _write_json(args.report, rep)
        say(f"wrote {args.report}")
    return _verdict_exit(args, [rep["truth"]["line"]], [rep["verdict"]])


def _run_recorded(args: argparse.Namespace, scene: Any, say: Any) -> Any:
    """The deterministic run with the recorder on its frame hook (the run computes the same)."""
    from hapticloud.core.studies import run as study
    from hapticloud.hardware.recording.runs import (
        frame_hook,
        record_ticks,
        recording_summary,
        scene_recorder,
    )

    recorder = scene_recorder(args.record, scene, "run", "scene")
    recorder.sink.blocking = True  # a simulated run has no deadline: wait, never drop
    try:
        record = study.run_scene(scene, None, args.duration, frame_sink=frame_hook(recorder.sink))
        record_ticks(recorder.sink, record)
    finally:
        result = recorder.close()
    say(recording_summary(result))
    return record


def _plot_single(record: Any, out: Path, say: Any, suffix: str = "") -> None:
    from hapticloud.app import plots

    name = record.scene.name
    say(f"wrote {plots.fig11_distance_velocity(record, out / f'fig11_{name}{suffix}.png')}")
    if record.info["cameras"]:
        say(f"wrote {plots.fig8_fusion(record, out / f'fig8_{name}{suffix}.png')}")
