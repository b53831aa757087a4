"""``hapticloud replay RECORDING``: perception and fusion re-run on recorded frames, compared."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from . import add_set_option, check_outputs, overrides


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "replay",
        help="re-run perception and fusion on a recording's depth frames, other parameters "
        "allowed, and compare with what was recorded",
        description="Reads RECORDING's camera frames (with the HIP and the robot's shapes at "
        "capture) and runs each camera's frames, in order, through a fresh pipeline with the "
        "recording's parameters, changed by --preset and --set. Compares each new estimate with "
        "the recorded one (max_centroid_diff_mm; 0 with the recording's own parameters) and "
        "the fused surfaces of both. Parameters needing pixels the recording did not store "
        "(a larger workspace than an ROI recording kept) are counted as roi_exceeded.",
    )
    parser.add_argument("recording", metavar="RECORDING", help="the .mcap recording")
    parser.add_argument(
        "--preset",
        metavar="FILE.toml",
        help="parameters to use: [perception] and [fusion] tables as in a scene file",
    )
    parser.add_argument("--start", type=float, metavar="S", help="from this recording time (s)")
    parser.add_argument("--end", type=float, metavar="S", help="until this recording time (s)")
    parser.add_argument(
        "--report",
        metavar="PATH",
        help="write the JSON report here: the figures and every frame's recorded and new estimate",
    )
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_set_option(parser, "perception.voxel.voxel_size_m=0.004")
    parser.set_defaults(handler=run)


def _preset(path: str | None) -> dict[str, Any] | None:
    import tomllib

    from hapticloud.core.errors import ConfigError

    if path is None:
        return None
    try:
        return tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ConfigError(f"--preset {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"--preset {path}: cannot be read as text ({err})") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"--preset {path}: not valid TOML ({err})") from None


def _deg(value: Any) -> str:
    return "n/a" if value is None else f"{value:.2f} deg"


def _est(est: Any) -> dict[str, Any]:
    return {
        "valid": bool(est.valid),
        "centroid": [float(x) for x in est.centroid],
        "normal": [float(x) for x in est.normal],
        "reason": est.reason,
    }


def run(args: argparse.Namespace) -> int:
    import time

    from hapticloud.core.recording import replay, replay_configs
    from hapticloud.hardware.recording.reader import Recording

    say = (lambda *_: None) if args.quiet else (lambda line: print(line, flush=True))
    check_outputs(files={"--report": args.report})
    preset = _preset(args.preset)
    with Recording.open(args.recording) as rec:
        perception, fusion = replay_configs(rec.config_toml(), preset, overrides(args.set))
        if not rec.finished:
            say(f"{args.recording}: unfinished recording, replaying up to its last whole chunk")
        recorded = {(e.camera, e.seq): e for e in rec.estimates(None, args.start, args.end)}
        wall0 = time.perf_counter()
        result = replay(rec.frames(None, args.start, args.end), recorded, perception, fusion)
        wall = time.perf_counter() - wall0
        span = rec.duration_s
    summary = result.summary()
    rows = result.rows
    covered = (rows[-1].t - rows[0].t) if len(rows) > 1 else 0.0
    summary["wall_time_s"] = wall
    summary["real_time_factor"] = covered / wall if wall > 0 and covered > 0 else None
    summary["recording_duration_s"] = span

    def mm(value: Any) -> str:
        return "n/a" if value is None else f"{value:.3f} mm"

    say(
        f"replayed {summary['frames']} frames "
        f"({', '.join(f'{k} {v}' for k, v in summary['frames_per_camera'].items()) or 'none'}) "
        f"in {wall:.2f} s"
        + (
            f" ({summary['real_time_factor']:.1f}x real time)"
            if summary["real_time_factor"]
            else ""
        )
    )
    say(
        f"identical to the recorded estimate: {summary['identical']} of "
        f"{summary['with_recorded_estimate']}; both valid {summary['both_valid']}, valid only "
        f"recorded {summary['valid_recorded_only']}, only new {summary['valid_new_only']}"
    )
    say(
        f"max_centroid_diff_mm {mm(summary['max_centroid_diff_mm'])} (median "
        f"{mm(summary['median_centroid_diff_mm'])}), max normal diff "
        f"{_deg(summary['max_normal_diff_deg'])}, "
        f"max fused diff {mm(summary['max_fused_diff_mm'])}"
    )
    if summary["roi_exceeded"]:
        say(
            f"{summary['roi_exceeded']} frames: the new crop reads pixels the recording did not "
            "store (its ROI); there the re-run saw less than the camera did"
        )
    if args.report:
        report = {
            "recording": args.recording,
            "summary": summary,
            "perception": perception.to_dict(),
            "fusion": fusion.to_dict(),
            "frames": [
                {
                    "camera": r.camera,
                    "seq": r.seq,
                    "t": r.t,
                    "roi_exceeded": r.roi_exceeded,
                    "recorded": None if r.recorded is None else _est(r.recorded),
                    "new": _est(r.new),
                }
                for r in rows
            ],
        }
        Path(args.report).parent.mkdir(parents=True, exist_ok=True)
        Path(args.report).write_text(json.dumps(report, indent=1))
        say(f"wrote {args.report}")
    return 0
