"""Reading a scene file: TOML -> validated :class:`Scene`, with ``--set`` overrides.

Every problem raises :class:`~hapticloud.core.errors.ConfigError` with one line naming the file
and the key, e.g. ``assets/scenes/wall.toml: robot.hip_radius_m = -1.0: must be in [0.0, 0.2] m``
or ``scene.toml: cameras[1].decimaton: unknown key (allowed: ...)``.

Overrides use the same dotted keys as the file: ``surface.speed_mps=2.0``,
``haptics.velocity.kv=5``, ``perception.crop.workspace_radius_m=0.3``. Entries of a list are named
by their ``name`` or their index: ``cameras.front.decimation=1``, ``walls.0.level=fixed``,
``patient.waypoints.2.speed_mps=0.8``. A table that declares something (``[surface]``,
``[patient]``, a list entry) must exist in the file to be overridden: an override never adds a
camera, a body or a moving surface the scene did not declare.

A scene declares at least what it is (a ``[scene]`` table) or something the HIP can touch (a body,
a wall, the moving surface): an empty file is refused (``scene.toml: scene is empty: ...``).
"""

from __future__ import annotations

import copy
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hapticloud.assets import asset_path

from ..config import StageConfig
from ..errors import ConfigError
from .schema import (
    BodySpec,
    CameraSpec,
    SceneConfig,
    WallSpec,
    WaypointSpec,
)

#: The least a scene declares: what it is, or something the HIP can touch.
_MINIMUM = "declare a [scene] table or something to touch ([[bodies]], [[walls]] or [surface])"

#: Top-level arrays of tables and the class of each entry.
LIST_TABLES: dict[str, type[StageConfig]] = {
    "cameras": CameraSpec,
    "bodies": BodySpec,
    "background": BodySpec,
    "walls": WallSpec,
}


@dataclass(frozen=True)
class Scene:
    """A validated scene: the fixed tables, the lists, and what the file declared.

    ``declared`` holds the optional tables present in the file (``"patient"``, ``"surface"``);
    absent ones keep their defaults in :attr:`config` but are not built. ``data`` is the
    (overridden) TOML content, kept for the report.
    """

    path: str
    config: SceneConfig
    cameras: tuple[CameraSpec, ...] = ()
    bodies: tuple[BodySpec, ...] = ()
    background: tuple[BodySpec, ...] = ()
    walls: tuple[WallSpec, ...] = ()
    waypoints: tuple[WaypointSpec, ...] = ()
    declared: frozenset[str] = frozenset()
    data: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def name(self) -> str:
        return self.config.scene.name

    @property
    def has_patient(self) -> bool:
        return "patient" in self.declared

    @property
    def has_surface(self) -> bool:
        return "surface" in self.declared

    def with_overrides(self, overrides: Mapping[str, Any]) -> Scene:
        """A copy with ``--set`` overrides applied (see the module docstring)."""
        if not overrides:
            return self
        data = copy.deepcopy(dict(self.data))
        for key, value in overrides.items():
            _set_path(data, key, value)
        try:
            return parse_scene(data, self.path)
        except ConfigError as err:
            keys = ", ".join(overrides)
            raise ConfigError(f"{self.path} with --set {keys}: {err}") from None


def scenes_dir() -> Path:
    """The shipped scene files' folder (``hapticloud.assets/scenes``)."""
    return asset_path("scenes")


def resolve_scene(name: str | Path) -> Path:
    """A scene file path: ``name`` itself if it exists, else a shipped scene called ``name``.

    ``"wall"``, ``"wall.toml"`` and ``"assets/scenes/wall.toml"`` all name the shipped wall scene.
    """
    path = Path(name)
    if path.exists():
        return path
    shipped = scenes_dir() / (path.name if path.suffix == ".toml" else f"{path.name}.toml")
    return shipped if shipped.is_file() else path


def load_scene(path: str | Path, overrides: Mapping[str, Any] | None = None) -> Scene:
    """Read and validate a scene file, then apply ``overrides``.

    Raises
    ------
    ConfigError
        One line naming the file and the key (missing file, bad TOML, unknown key, wrong type,
        value out of range, inconsistent tables).
    """
    path = resolve_scene(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such scene file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, not a scene file") from None
    except UnicodeDecodeError as err:
        kind = "a recording (.mcap), not a scene file" if path.suffix == ".mcap" else "not text"
        raise ConfigError(
            f"{path}: {kind} (byte {err.start} is not UTF-8): expected a scene file (TOML)"
        ) from None
    except OSError as err:
        raise ConfigError(
            f"{path}: cannot be read ({err.strerror or type(err).__name__})"
        ) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML ({err})") from None
    try:
        scene = parse_scene(data, str(path))
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None
    return scene.with_overrides(overrides or {})


def _entries(data: Mapping[str, Any], key: str, cls: type[StageConfig], where: str) -> tuple:
    items = data.get(key, [])
    if not isinstance(items, list) or not all(isinstance(i, Mapping) for i in items):
        raise ConfigError(f"{where}: expected an array of tables ([[{where}]])")
    return tuple(cls.from_dict(item, where=f"{where}[{i}]") for i, item in enumerate(items))


def _unique(names: list[str], what: str) -> None:
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ConfigError(f"{what}: names must be unique, repeated: {', '.join(dupes)}")


def parse_scene(data: Mapping[str, Any], path: str = "<scene>") -> Scene:
    """Validate already-parsed TOML data (errors name the key, not the file)."""
    if not isinstance(data, Mapping):
        raise ConfigError("expected a table at the top level")
    fixed = {k: v for k, v in data.items() if k not in LIST_TABLES}
    patient = fixed.get("patient")
    waypoints: tuple[WaypointSpec, ...] = ()
    if patient is not None:
        if not isinstance(patient, Mapping):
            raise ConfigError(f"patient: expected a table, got {patient!r}")
        patient = dict(patient)
        waypoints = _entries(patient, "waypoints", WaypointSpec, "patient.waypoints")
        patient.pop("waypoints", None)
        fixed["patient"] = patient
    config = SceneConfig.from_dict(fixed)
    lists = {key: _entries(data, key, cls, key) for key, cls in LIST_TABLES.items()}
    cameras, bodies, background, walls = (
        lists["cameras"],
        lists["bodies"],
        lists["background"],
        lists["walls"],
    )
    declared = frozenset(k for k in SceneConfig.OPTIONAL_TABLES if k in data)
    _unique([c.name for c in cameras], "cameras")
    body_names = [b.name for b in (*bodies, *background)]
    if "surface" in declared:
        body_names.append(config.surface.name)
    _unique(body_names, "bodies")
    _unique([w.name for w in walls], "walls")
    if waypoints and "patient" not in declared:  # pragma: no cover - waypoints live in [patient]
        raise ConfigError("patient.waypoints: need a [patient] table")
    if cameras and not (bodies or "surface" in declared):
        raise ConfigError("cameras: the scene has cameras but nothing to see (no [[bodies]])")
    if not ("scene" in data or bodies or walls or "surface" in declared):
        what = "no [scene] table and nothing to touch" if data else "scene is empty"
        raise ConfigError(f"{what}: {_MINIMUM}")
    for i, wp in enumerate(waypoints):
        if i > 0 and wp.t_s < 0.0 and wp.speed_mps == 0.0:
            raise ConfigError(f"patient.waypoints[{i}]: give t_s or speed_mps")
    return Scene(
        path=path,
        config=config,
        cameras=cameras,
        bodies=bodies,
        background=background,
        walls=walls,
        waypoints=waypoints,
        declared=declared,
        data=copy.deepcopy(dict(data)),
    )


def _set_path(data: dict[str, Any], dotted: str, value: Any) -> None:
    """Set ``dotted`` in the raw scene data (see the module docstring for list entries)."""
    parts = dotted.split(".")
    if len(parts) < 2 or not all(parts):
        raise ConfigError(f"--set {dotted}: expected table.key=value")
    head = parts[0]
    if head in LIST_TABLES or (head == "patient" and len(parts) > 2 and parts[1] == "waypoints"):
        if head == "patient":
            container = data.get("patient", {}).get("waypoints", [])
            label, rest = "patient.waypoints", parts[2:]
        else:
            container = data.get(head, [])
            label, rest = head, parts[1:]
        if len(rest) < 2:
            raise ConfigError(f"--set {dotted}: name the entry and the key ({label}.NAME.key)")
        entry = _find_entry(container, rest[0], label, dotted)
        _set_in(entry, rest[1:], value, dotted)
        return
    if head in SceneConfig.OPTIONAL_TABLES and head not in data:
        raise ConfigError(f"--set {dotted}: the scene declares no [{head}] table")
    _set_in(data, parts, value, dotted)


def _find_entry(container: Any, selector: str, label: str, dotted: str) -> dict[str, Any]:
    if not isinstance(container, list) or not container:
        raise ConfigError(f"--set {dotted}: the scene declares no {label}")
    for i, entry in enumerate(container):
        if isinstance(entry, dict) and (entry.get("name") == selector or str(i) == selector):
            return entry
    names = [str(e.get("name", i)) for i, e in enumerate(container) if isinstance(e, dict)]
    raise ConfigError(f"--set {dotted}: no {label} entry {selector!r} (have {', '.join(names)})")


def _set_in(table: dict[str, Any], parts: list[str], value: Any, dotted: str) -> None:
    for part in parts[:-1]:
        nxt = table.setdefault(part, {})
        if not isinstance(nxt, dict):
            raise ConfigError(f"--set {dotted}: '{part}' is a value, not a table")
        table = nxt
    table[parts[-1]] = value


__all__ = ["LIST_TABLES", "Scene", "load_scene", "parse_scene", "resolve_scene", "scenes_dir"]
