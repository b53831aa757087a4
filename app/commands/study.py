"""``hapticloud study``: the speed/accuracy trade of several knobs together, on Dask.

``--grid KEY=V1,V2`` (repeatable: the full product) or ``--search nsga2 --trials N --space
KEY=LO:HI[:log]``; each trial measured side by side on the same frames
(:mod:`hapticloud.core.studies.trade`), run on a Dask cluster and cached
(:mod:`hapticloud.hardware.study`). ``--extremes`` runs every knob at its bounds instead.
docs/trade-study.md explains the output and the presets.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hapticloud.core.errors import ConfigError

from . import check_outputs, positive_float, positive_int

DEFAULT_FRAMES = 15
EXTREME_SCENES = ("sphere_head_occluded", "cylinder_arm", "tilted_torso_occluded")
EXTREME_BUDGET_MM = 10.0


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "study",
        help="speed/accuracy trade of several knobs together (grid or NSGA-II, on Dask)",
        description="Measures trials of perception, fusion and control knobs (the dotted names "
        "of --set) side by side on the same frames: latency from the depth frame, accuracy "
        "against the simulator's truth, and for closed-loop knobs the true minimum margin and "
        "tracking error of a short run. Prints every trial with the non-dominated ones marked *, "
        "unsafe ones ! (never on the front). Trials run on an embedded Dask cluster sized to the "
        "machine, or on --scheduler; finished trials are cached and a rerun resumes.",
    )
    what = parser.add_argument_group("what to study")
    what.add_argument(
        "--grid",
        action="append",
        default=[],
        metavar="KEY=V1,V2,...",
        help="values of one knob (repeatable: every combination is a trial)",
    )
    what.add_argument("--search", choices=("nsga2",), help="search the --space ranges")
    what.add_argument(
        "--space",
        action="append",
        default=[],
        metavar="KEY=LO:HI[:log]",
        help="range of one numeric knob for --search (repeatable)",
    )
    what.add_argument("--trials", type=positive_int, default=64, metavar="N", help="(64)")
    what.add_argument(
        "--population", type=positive_int, default=16, metavar="N", help="NSGA-II (16)"
    )
    what.add_argument("--seed", type=int, default=0, help="the search's seed (0)")
    what.add_argument(
        "--extremes",
        action="store_true",
        help="every knob at its lower and upper bound (and interacting pairs): no exception, "
        "no NaN, valid within budget or invalid with a reason; prints the failing cases",
    )
    what.add_argument(
        "--knobs",
        metavar="KEY,...",
        help="with --extremes: only these knobs (default: every knob)",
    )
    where = parser.add_argument_group("measured on")
    where.add_argument(
        "--scenes",
        metavar="NAME,...",
        help="study scenes (default: all; --extremes: " + ",".join(EXTREME_SCENES) + ")",
    )
    where.add_argument(
        "--recording",
        action="append",
        default=[],
        metavar="FILE.mcap",
        help="also (without --scenes: only) re-run perception on this recording's frames "
        "(repeatable; --frames per camera), scored against its truth if simulated, else against "
        "its recorded estimates",
    )
    where.add_argument(
        "--frames",
        type=positive_int,
        default=DEFAULT_FRAMES,
        metavar="N",
        help=f"frames per scene, any N >= 1 ({DEFAULT_FRAMES})",
    )
    where.add_argument(
        "--loop-duration",
        type=positive_float,
        default=None,
        metavar="S",
        help="closed-loop knobs: simulated s of the closed-loop scene (1.5)",
    )
    run = parser.add_argument_group("running")
    run.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="a running Dask scheduler")
    run.add_argument(
        "--workers", type=positive_int, metavar="N", help="embedded cluster (default: cores)"
    )
    run.add_argument("--cache", metavar="DIR", help="trial cache (~/.cache/hapticloud/study)")
    run.add_argument("--no-cache", action="store_true", help="measure every trial again")
    run.add_argument(
        "--resume",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="reuse finished trials and the search's journal (default on)",
    )
    run.add_argument("--yes", action="store_true", help="allow more than 10,000 trials")
    out = parser.add_argument_group("output")
    out.add_argument("--json", metavar="OUT", help="write trials and front as JSON")
    out.add_argument("--plot", metavar="DIR", help="write front.png and one plot per knob")
    out.add_argument(
        "--write-presets", metavar="DIR", help="write fast.toml, balanced.toml, accurate.toml"
    )
    parser.set_defaults(handler=run_study)


# ----- checking the request (nothing has started) ------------------------------------------------
@dataclasses.dataclass(frozen=True)
class _Request:
    specs: list[Any]
    keys: list[str]
    default_index: int | None
    space: list[Any]
    template: Any
    extremes: list[str]


def _scenes(args: argparse.Namespace) -> tuple[str, ...]:
    from hapticloud.core.studies.trade.evaluate import check_scenes, study_scenes

    if args.scenes is None and args.recording:
        return ()
    if args.scenes is None:
        return EXTREME_SCENES if args.extremes else tuple(study_scenes())
    return check_scenes([s.strip() for s in args.scenes.split(",") if s.strip()])


def _request(args: argparse.Namespace) -> _Request:
    from hapticloud.core.studies.trade import knobs as k
    from hapticloud.core.studies.trade.evaluate import LOOP_DURATION_S, TrialSpec, shipped_default

    modes = [bool(args.grid), bool(args.search), bool(args.extremes)]
    if sum(modes) != 1:
        raise ConfigError("study: give one of --grid, --search nsga2 or --extremes")
    if args.space and not args.search:
        raise ConfigError("--space: only with --search nsga2")
    if args.search and not args.space:
        raise ConfigError("--search nsga2: give the ranges with --space KEY=LO:HI[:log]")
    loop_s = LOOP_DURATION_S if args.loop_duration is None else args.loop_duration
    recordings = _recordings(args)
    template = TrialSpec(
        {}, _scenes(args), args.frames, loop_duration_s=loop_s, recordings=recordings
    )
    if args.extremes:
        chosen = None if args.knobs is None else [s.strip() for s in args.knobs.split(",")]
        cases = k.extreme_cases(chosen)
        specs = [dataclasses.replace(template, params=p, companions=False) for _, p in cases]
        return _Request(specs, [], None, [], template, [label for label, _ in cases])
    if args.search:
        space = [k.parse_space(text) for text in args.space]
        if len({r.key for r in space}) != len(space):
            raise ConfigError("--space: a knob given twice")
        if args.trials > k.MAX_TRIALS_UNASKED and not args.yes:
            raise ConfigError(f"--trials {args.trials}: over {k.MAX_TRIALS_UNASKED:,}; add --yes")
        return _Request([], [r.key for r in space], None, space, template, [])
    grids = [k.parse_grid(text) for text in args.grid]
    size = k.grid_size(grids)
    if size > k.MAX_TRIALS_UNASKED and not args.yes:
        raise ConfigError(f"--grid: {size:,} trials, over {k.MAX_TRIALS_UNASKED:,}; add --yes")
    trials = k.grid_trials(grids)
    keys = list(dict(grids))
    default = {key: shipped_default(key) for key in keys}
    if default not in trials:
        trials.append(default)  # the shipped default is always measured beside the grid
    specs = [dataclasses.replace(template, params=p) for p in trials]
    return _Request(specs, keys, trials.index(default), [], template, [])


def _recordings(args: argparse.Namespace) -> tuple[str, ...]:
    if not args.recording:
        return ()
    from hapticloud.hardware.study.recording import recording_id

    turned = [g.partition("=")[0].strip() for g in args.grid] + [
        s.partition("=")[0].strip() for s in args.space
    ]
    if "camera.decimation" in turned:
        raise ConfigError("--recording: camera.decimation cannot re-render recorded frames")
    return tuple(dict.fromkeys(recording_id(path) for path in args.recording))


# ----- running -----------------------------------------------------------------------------------
class _Progress:
    """tqdm bar: trials done, the best figure so far, the ETA (tqdm's)."""

    def __init__(self, total: int, label: str) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=total, desc=label, unit="trial", file=sys.stderr, dynamic_ncols=True)
        self.best: tuple[float, float] | None = None

    def __call__(self, _index: int, result: Any) -> None:
        o = result.objectives
        err, lat = o.get("centroid_mm_p90", math.nan), o.get("latency_ms_median", math.nan)
        if not result.unsafe and math.isfinite(err) and (self.best is None or err < self.best[0]):
            self.best = (err, lat)
        if self.best is not None:
            self.bar.set_postfix_str(
                f"best c_p90 {self.best[0]:.2f} mm @ {self.best[1]:.2f} ms", refresh=False
            )
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


def _cache(args: argparse.Namespace) -> Any:
    from hapticloud.hardware.study.cache import TrialCache, default_cache_dir

    folder = Path(args.cache) if args.cache else default_cache_dir()
    return TrialCache(None if args.no_cache or not args.resume else folder), folder


def run_study(args: argparse.Namespace) -> int:
    check_outputs(
        files={"--json": args.json},
        folders={"--plot": args.plot, "--write-presets": args.write_presets},
    )
    if args.extremes and (args.write_presets or args.plot):
        raise ConfigError("--extremes: no front to plot or write presets from")
    request = _request(args)
    from hapticloud.hardware.study.cluster import open_client, worker_count
    from hapticloud.hardware.study.runner import run_trials
    from hapticloud.hardware.study.search import nsga2

    cache, cache_dir = _cache(args)
    started = time.perf_counter()
    with open_client(args.scheduler, args.workers) as client:
        workers = worker_count(client)
        where = args.scheduler or f"embedded LocalCluster, {workers} workers"
        n = args.trials if args.search else len(request.specs)
        print(f"study: {n} trials on {where}", file=sys.stderr)
        progress = _Progress(n, "extremes" if args.extremes else "trials")
        try:
            if args.search:
                journal = None if args.no_cache else cache_dir / "nsga2.journal"
                outcome = nsga2(
                    client,
                    request.space,
                    request.template,
                    args.trials,
                    cache,
                    journal=journal,
                    resume=args.resume,
                    seed=args.seed,
                    population=args.population,
                    on_done=progress,
                )
            else:
                budget = EXTREME_BUDGET_MM if args.extremes else None
                outcome = run_trials(client, request.specs, cache, progress, budget_mm=budget)
        finally:
            progress.close()
    wall_s = time.perf_counter() - started
    if outcome.interrupted:
        print(
            f"study: stopped by Ctrl-C; {len(outcome.finished)} trials finished and kept",
            file=sys.stderr,
        )
    if args.extremes:
        return _report_extremes(request, outcome, wall_s)
    return _report(args, request, outcome, workers, wall_s)


# ----- output ------------------------------------------------------------------------------------
def _command(args: argparse.Namespace) -> str:
    """The command line that reproduces this study (what presets and docs quote)."""
    parts = ["hapticloud study"]
    parts += [f"--grid {g}" for g in args.grid]
    if args.search:
        parts += [f"--search {args.search} --trials {args.trials}"]
        parts += [f"--space {s}" for s in args.space]
        parts += [f"--population {args.population} --seed {args.seed}"]
    if args.scenes:
        parts.append(f"--scenes {args.scenes}")
    parts += [f"--recording {path}" for path in args.recording]
    parts.append(f"--frames {args.frames}")
    return " ".join(parts)


def _report(
    args: argparse.Namespace, request: _Request, outcome: Any, workers: int, wall_s: float
) -> int:
    from hapticloud.core.studies.trade import front as fr
    from hapticloud.core.studies.trade.evaluate import shipped_default

    trials = outcome.finished
    if args.search:
        # NSGA-II asks for a parameter set again now and then: each is shown once.
        unique = {json.dumps(t.params, sort_keys=True): t for t in reversed(trials)}
        trials = [t for t in trials if unique.get(json.dumps(t.params, sort_keys=True)) is t]
        default = {key: shipped_default(key) for key in request.keys}
        index = [i for i, t in enumerate(trials) if _same(t.params, default)]
        default_index = index[0] if index else None
    else:
        default_index = request.default_index
        if default_index is not None and outcome.results[default_index] is None:
            default_index = None
        elif default_index is not None:
            default_index = sum(r is not None for r in outcome.results[:default_index])
    front = fr.pareto_front(trials)
    presets = fr.pick_presets(trials, front, default_index)
    print(
        f"{len(trials)} distinct trials ({outcome.cached} from the cache, {outcome.measured} "
        f"measured) in {wall_s:.1f} s on {workers} workers; {_sources(request, trials)}; front "
        f"over {', '.join(fr.front_objectives(trials))}: {len(front)} non-dominated (*), "
        f"{sum(x.unsafe for x in trials)} unsafe (!)"
    )
    for rec, ref in _references(request).items():
        print(f"recording {rec.split('#')[0]}: scored against {ref}")
    print(fr.format_table(trials, front, request.keys, presets))
    if default_index is not None:
        print(f"shipped default: trial with {dict(trials[default_index].params)}")
    command = _command(args)
    if args.json:
        _write_json(args.json, trials, front, presets, default_index, request, command, wall_s)
    if args.plot:
        from hapticloud.app.commands.study_plot import plot_front, plot_knobs

        folder = Path(args.plot)
        folder.mkdir(parents=True, exist_ok=True)
        names = ", ".join(fr.front_objectives(trials))
        plot_front(folder / "front.png", trials, front, default_index, presets, command, names)
        plot_knobs(folder, trials, front, request.keys)
        print(f"plots: {folder}/front.png and {len(request.keys)} knob plots")
    if args.write_presets:
        _write_presets(Path(args.write_presets), trials, presets, request, command)
    return 0


def _sources(request: _Request, trials: Sequence[Any]) -> str:
    """What each trial ran on: frames per scene, recordings, estimates per trial."""
    t = request.template
    parts = []
    if t.scenes:
        parts.append(f"{t.frames} frames per scene x {len(t.scenes)} scenes")
    if t.recordings:
        parts.append(f"the first {t.frames} frames per camera of {len(t.recordings)} recording(s)")
    used = max((x.estimates for x in trials), default=0)
    return " + ".join(parts) + f" = {used} estimates per trial"


def _references(request: _Request) -> dict[str, str]:
    """What each recording's frames are scored against, by recording."""
    if not request.template.recordings:
        return {}
    from hapticloud.hardware.study.recording import reference

    return {rec: reference(rec) for rec in request.template.recordings}


def _same(a: Any, b: Any) -> bool:
    return all(math.isclose(float(a[k]), float(b[k]), rel_tol=1e-9) for k in b) if a else False


def _write_json(
    path: str,
    trials: Sequence[Any],
    front: Sequence[int],
    presets: dict[str, int],
    default_index: int | None,
    request: _Request,
    command: str,
    wall_s: float,
) -> None:
    from hapticloud.hardware.study.cache import code_version

    rows = []
    for i, t in enumerate(trials):
        row = t.to_json()
        row["front"] = i in front
        row["default"] = i == default_index
        rows.append(row)
    payload = {
        "command": command,
        "code_version": code_version(),
        "scenes": list(request.template.scenes),
        "recordings": [
            {"path": rec.split("#")[0], "id": rec, "scored_against": ref}
            for rec, ref in _references(request).items()
        ],
        "frames_per_scene": request.template.frames,
        "wall_s": round(wall_s, 1),
        "trials": rows,
        "front": [rows[i] for i in front],
        "presets": {name: rows[i]["params"] for name, i in presets.items()},
    }
    Path(path).write_text(json.dumps(payload, indent=1))


def _write_presets(
    folder: Path, trials: Sequence[Any], presets: dict[str, int], request: _Request, command: str
) -> None:
    from hapticloud.core.studies.trade import front as fr
    from hapticloud.core.studies.trade.knobs import split_camera, with_companions

    if not presets:
        raise ConfigError("--write-presets: no trial on the front (every trial unsafe)")
    folder.mkdir(parents=True, exist_ok=True)
    rules = {
        "fast": f"the fastest front point with centroid p90 <= {fr.ACCURACY_TARGET_MM:g} mm",
        "balanced": "the front's knee (nearest the ideal, both figures scaled to the front)",
        "accurate": f"the most accurate front point within {fr.ACCURATE_LATENCY_FACTOR:g}x the "
        "default's latency",
    }
    for name in fr.PRESETS:
        o = trials[presets[name]].objectives
        header = [
            f"hapticloud preset '{name}': {rules[name]} (docs/trade-study.md).",
            f"Made by: {command} --write-presets DIR",
            f"Measured: latency {o['latency_ms_median']:.2f} ms median, centroid "
            f"{o['centroid_mm_median']:.2f} mm median / {o['centroid_mm_p90']:.2f} mm p90, "
            f"normal {o['normal_deg_median']:.2f} deg, valid {100 * o['valid_share']:.0f} %.",
            "Every parameter not listed keeps its shipped default.",
        ]
        params, camera = split_camera(trials[presets[name]].params)
        turned = {k: v for k, v in camera.items() if f"camera.{k}" in request.keys}
        if turned:
            # A parameter file holds no camera: the scene's cameras carry these.
            header.append(
                "Measured with the camera's "
                + ", ".join(f"{k} = {v}" for k, v in turned.items())
                + ": set it on the scene's cameras (cameras.<name>."
                + ", cameras.<name>.".join(turned)
                + ")."
            )
        params = with_companions(params)
        (folder / f"{name}.toml").write_text(fr.preset_toml(params, header))
    print(f"presets: {', '.join(f'{folder}/{n}.toml' for n in fr.PRESETS)}")


def _report_extremes(request: _Request, outcome: Any, wall_s: float) -> int:
    failing = []
    refused: list[str] = []
    for label, result in zip(request.extremes, outcome.results, strict=True):
        if result is None:
            continue
        if any(r.startswith("refused") for r in result.reasons):
            refused.append(f"refused {label}: {result.reasons[0]}")
        problems = list(result.problems)
        measured = result.objectives.get("valid_share", math.nan) > 0
        if measured and not math.isfinite(result.objectives.get("latency_ms_median", math.nan)):
            problems.append("NaN latency")
        if not result.reasons and not all(
            math.isfinite(v) for n, v in result.objectives.items() if n in _MEASURED
        ):
            problems.append("NaN in the figures of a valid trial")
        if problems:
            failing.append((label, problems))
    done = len(outcome.finished)
    print(
        f"extremes: {done} cases in {wall_s:.1f} s ({len(refused)} refused with their reason), "
        f"{len(failing)} failing; {_sources(request, outcome.finished)}"
    )
    for rec, ref in _references(request).items():
        print(f"recording {rec.split('#')[0]}: scored against {ref}")
    for line in refused:
        print(line)
    for label, problems in failing:
        more = f" (+{len(problems) - 1} more)" if len(problems) > 1 else ""
        print(f"FAIL {label}: {problems[0]}{more}")
    return 1 if failing or outcome.interrupted else 0


_MEASURED = ("latency_ms_median", "latency_ms_p90", "centroid_mm_median", "centroid_mm_p90")
