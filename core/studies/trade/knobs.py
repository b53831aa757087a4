"""The knobs a trade study may turn: their names, ranges, and the trials built from them.

A knob is any parameter of the ``perception``, ``fusion``, ``haptics`` or ``controller`` tables,
named as ``--set`` names it (``perception.voxel.voxel_size_m``); its range and kind come from the
parameter's declaration (:func:`~hapticloud.core.config.param`), so the study refuses exactly
what a scene file would. Perception knobs are measured on camera frames; the others act in the
closed loop and are measured by a short deterministic run (:data:`CLOSED_LOOP_TABLES`). The
study camera's own settings are knobs too (:data:`CAMERA_KNOBS`: ``camera.decimation``, what a
scene file sets as ``cameras.<name>.decimation``): they change the frames themselves.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

from ...config import ParamInfo, parse_override
from ...errors import ConfigError
from ...scene import SceneConfig
from ...scene.schema import CameraSpec

#: The tables whose parameters are knobs.
KNOB_TABLES = ("perception", "fusion", "haptics", "controller")
#: Tables whose knobs only show in the closed loop (not in a camera frame's estimate).
CLOSED_LOOP_TABLES = ("fusion", "haptics", "controller")
#: Knobs of the camera the study's frames are rendered with (a scene's ``cameras.<name>.<param>``,
#: the range of :class:`~hapticloud.core.scene.schema.CameraSpec`); the default is the benchmark
#: camera's (full resolution), not a scene file's.
CAMERA_TABLE = "camera"
CAMERA_DEFAULTS: dict[str, Any] = {"decimation": 1}
#: A grid larger than this needs ``--yes``.
MAX_TRIALS_UNASKED = 10_000

#: Cross-field rules of the perception table, and the companion that keeps a trial inside them:
#: (knob, companion, why). A trial that raises the knob past its companion raises the companion
#: with it (as ``bench perception --knobs`` does), so no trial is wasted on a refused config.
COMPANIONS: tuple[tuple[str, str], ...] = (
    ("perception.abstraction.r_out_m", "perception.crop.workspace_radius_m"),
    ("perception.reconstruction.r_out_m", "perception.crop.workspace_radius_m"),
    ("perception.voxel.voxel_size_m", "perception.max_spacing_m"),
)

#: Knobs that bound each other (lower, upper): the extremes put them at the closest legal pair.
INTERACTING_PAIRS: tuple[tuple[str, str], ...] = (
    ("perception.abstraction.r_in_m", "perception.abstraction.r_out_m"),
    ("perception.reconstruction.r_in_m", "perception.reconstruction.r_out_m"),
    ("perception.crop.min_depth_m", "perception.crop.max_depth_m"),
    ("haptics.velocity.v_min_mps", "haptics.velocity.v_max_mps"),
    ("perception.voxel.voxel_size_m", "perception.max_spacing_m"),
)


@dataclass(frozen=True)
class SearchRange:
    """One ``--space`` entry: a numeric knob searched between ``lo`` and ``hi``."""

    key: str
    lo: float
    hi: float
    log: bool
    integer: bool


def _camera_knobs() -> dict[str, ParamInfo]:
    infos = {p.name: p for p in CameraSpec.params()}
    return {
        f"{CAMERA_TABLE}.{name}": replace(
            infos[name], path=f"{CAMERA_TABLE}.{name}", default=default
        )
        for name, default in CAMERA_DEFAULTS.items()
    }


CAMERA_KNOBS: dict[str, ParamInfo] = _camera_knobs()


def knob_infos() -> dict[str, ParamInfo]:
    """Every knob by dotted name."""
    infos = {p.path: p for p in SceneConfig.params() if p.path.split(".")[0] in KNOB_TABLES}
    return {**infos, **CAMERA_KNOBS}


def is_camera(key: str) -> bool:
    return key.split(".")[0] == CAMERA_TABLE


def split_camera(params: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``params`` as (scene configuration overrides, camera settings by parameter name)."""
    scene = {k: v for k, v in params.items() if not is_camera(k)}
    camera = {**CAMERA_DEFAULTS}
    camera.update({k.split(".", 1)[1]: v for k, v in params.items() if is_camera(k)})
    return scene, camera


def knob(key: str) -> ParamInfo:
    """The knob named ``key``; :class:`ConfigError` naming the key when it is none."""
    infos = knob_infos()
    if key not in infos:
        import difflib

        close = difflib.get_close_matches(key, infos, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        tables = ", ".join(KNOB_TABLES)
        raise ConfigError(f"{key}: unknown knob{hint}; knobs are the parameters of {tables}")
    return infos[key]


def is_closed_loop(key: str) -> bool:
    return key.split(".")[0] in CLOSED_LOOP_TABLES


def with_companions(params: Mapping[str, Any]) -> dict[str, Any]:
    """``params`` plus the companions that keep it inside the cross-field rules (see
    :data:`COMPANIONS`); a companion the trial sets itself is left alone."""
    raised: dict[str, Any] = {}
    defaults = SceneConfig()
    for key, companion in COMPANIONS:
        if key in params and companion not in params:
            floor = float(params[key])
            if floor > max(float(defaults.get_path(companion)), raised.get(companion, 0.0)):
                raised[companion] = floor
    # Companions first: each override is checked against the config built so far.
    return {**raised, **params}


def trial_config(params: Mapping[str, Any]) -> SceneConfig:
    """The default scene configuration with the trial's knobs (and companions) applied (camera
    knobs apart: they are the frames', see :func:`split_camera`)."""
    return SceneConfig().with_overrides(with_companions(split_camera(params)[0]))


def _check_camera(key: str, value: Any) -> Any:
    name = key.split(".", 1)[1]
    # The camera table's own rules: the same message as a scene file's cameras.<name>.<param>.
    return CameraSpec().replace_path(name, value).get_path(name)


def check_value(key: str, value: Any) -> Any:
    """``value`` coerced to the knob's kind; :class:`ConfigError` if out of range."""
    knob(key)
    if is_camera(key):
        try:
            return _check_camera(key, value)
        except ConfigError as err:
            raise ConfigError(f"{CAMERA_TABLE}.{err}") from None
    try:
        return trial_config({key: value}).get_path(key)
    except ConfigError as with_companion:
        # Name the knob's own range when that is what refused it, not a raised companion's.
        SceneConfig().replace_path(key, value)
        raise with_companion from None


def _literal(key: str, raw: str) -> Any:
    return parse_override(f"{key}={raw}")[1]


def parse_grid(text: str) -> tuple[str, list[Any]]:
    """``KEY=V1,V2,...`` -> ``(KEY, [values])``, each value checked against the knob's range."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    items = [item.strip() for item in raw.split(",") if item.strip()]
    if not sep or not key:
        raise ConfigError(f"--grid {text!r}: expected KEY=V1,V2,...")
    if not items:
        raise ConfigError(f"--grid {text!r}: no values (an empty grid)")
    values = [check_value(key, _literal(key, item)) for item in items]
    return key, list(dict.fromkeys(values))


def parse_space(text: str) -> SearchRange:
    """``KEY=LO:HI[:log]`` -> :class:`SearchRange` (numeric knobs only, bounds in range)."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    parts = [p.strip() for p in raw.split(":")]
    if not sep or not key or len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] != "log"):
        raise ConfigError(f"--space {text!r}: expected KEY=LO:HI or KEY=LO:HI:log")
    info = knob(key)
    if info.kind not in (int, float):
        raise ConfigError(f"--space {key}: a {info.kind.__name__} knob; use --grid for it")
    lo, hi = (check_value(key, _literal(key, p)) for p in parts[:2])
    if not lo < hi:
        raise ConfigError(f"--space {text!r}: LO must be below HI")
    log = len(parts) == 3
    if log and lo <= 0:
        raise ConfigError(f"--space {text!r}: a log range needs LO > 0")
    return SearchRange(key, float(lo), float(hi), log, info.kind is int)


def grid_trials(grids: Sequence[tuple[str, Sequence[Any]]]) -> list[dict[str, Any]]:
    """The full product of the grids, one parameter dict per trial (a key given twice: the
    later values replace the earlier)."""
    merged = dict(grids)
    if not merged:
        return []
    keys = list(merged)
    return [dict(zip(keys, combo, strict=True)) for combo in itertools.product(*merged.values())]


def grid_size(grids: Sequence[tuple[str, Sequence[Any]]]) -> int:
    return math.prod(len(v) for v in dict(grids).values()) if grids else 0


# ----- extremes ----------------------------------------------------------------------------------
def _bounds(info: ParamInfo) -> list[Any]:
    if info.choices:
        return list(info.choices)
    if info.kind is bool:
        return [False, True]
    if info.kind not in (int, float) or info.lo is None or info.hi is None:
        return []
    lo, hi = info.kind(info.lo), info.kind(info.hi)
    if info.kind is float and not _accepted(info.path, lo):
        # An exclusive lower bound: the extreme is the closest value inside it.
        nudged = lo + 1e-6 * (hi - lo)
        lo = nudged if _accepted(info.path, nudged) else lo
    return [lo, hi]


def _accepted(key: str, value: Any) -> bool:
    try:
        check_value(key, value)
    except ConfigError:
        return False
    return True


def extreme_cases(keys: Iterable[str] | None = None) -> list[tuple[str, dict[str, Any]]]:
    """(label, params) for every knob at its lower and upper bound (every choice of a choice
    knob) and every interacting pair at its closest legal setting; ``keys`` limits the knobs."""
    infos = knob_infos()
    chosen = list(infos) if keys is None else [knob(k).path for k in keys]
    cases: list[tuple[str, dict[str, Any]]] = []
    for key in chosen:
        for value in _bounds(infos[key]):
            if value == infos[key].default:
                continue
            cases.append((f"{key}={value}", {key: value}))
    for lower, upper in INTERACTING_PAIRS:
        if lower not in chosen and upper not in chosen:
            continue
        default_upper = SceneConfig().get_path(upper)
        near = float(default_upper) * (1.0 - 1e-3)
        lo_info = infos[lower]
        if lo_info.hi is not None and near > lo_info.hi:
            continue
        cases.append((f"{lower}~{upper} ({near:g} vs {default_upper:g})", {lower: near}))
    return cases


__all__ = [
    "CAMERA_DEFAULTS",
    "CAMERA_KNOBS",
    "CAMERA_TABLE",
    "CLOSED_LOOP_TABLES",
    "COMPANIONS",
    "INTERACTING_PAIRS",
    "KNOB_TABLES",
    "MAX_TRIALS_UNASKED",
    "SearchRange",
    "check_value",
    "extreme_cases",
    "grid_size",
    "grid_trials",
    "is_camera",
    "is_closed_loop",
    "knob",
    "knob_infos",
    "parse_grid",
    "parse_space",
    "split_camera",
    "trial_config",
    "with_companions",
]
