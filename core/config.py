"""Parameters: one small frozen dataclass per stage, validated on construction, kept in TOML.

A stage declares its parameters with :func:`param`, which records the allowed range, the unit and
a one-line description in the field's metadata. That metadata is what validates a value, what the
GUI generates its sliders from, and what ``--set section.key=value`` overrides are checked against.

Example
-------
>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class VoxelConfig(StageConfig):
...     voxel_size_m: float = param(0.004, lo=0.0005, hi=0.05, unit="m", doc="voxel edge")
>>> VoxelConfig(voxel_size_m=0.01).voxel_size_m
0.01
>>> VoxelConfig(voxel_size_m=-1.0)
Traceback (most recent call last):
...
hapticloud.core.errors.ConfigError: voxel_size_m = -1.0: must be in [0.0005, 0.05] m
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar, Self

import tomli_w

from .errors import ConfigError

_MISSING = dataclasses.MISSING


def param(
    default: Any,
    *,
    lo: float | None = None,
    hi: float | None = None,
    unit: str = "",
    doc: str = "",
    choices: tuple[str, ...] | None = None,
    lo_open: bool = False,
    log_scale: bool = False,
    gui: bool = True,
) -> Any:
    """Declare one parameter of a stage.

    Parameters
    ----------
    default
        The shipped (tuned) value. Tuples are allowed for lists of numbers (each element checked).
    lo, hi
        Inclusive bounds (``lo_open`` makes the lower one exclusive).
    unit
        SI unit shown in the GUI and in error messages (``"m"``, ``"s"``, ``"1/s"``).
    doc
        One line saying what the parameter does.
    choices
        Allowed values of a string parameter.
    log_scale
        Hint for the GUI: the slider moves on a logarithmic scale.
    gui
        False hides the parameter from the generated panel.
    """
    meta = {
        "lo": lo,
        "hi": hi,
        "unit": unit,
        "doc": doc,
        "choices": choices,
        "lo_open": lo_open,
        "log_scale": log_scale,
        "gui": gui,
    }
    if isinstance(default, list):
        default = tuple(default)
    return field(default=default, metadata=meta)


def nested(cls: type[StageConfig]) -> Any:
    """Declare a sub-configuration field (``crop: CropConfig = nested(CropConfig)``)."""
    return field(default_factory=cls, metadata={"nested": True})


@dataclass(frozen=True)
class ParamInfo:
    """What the GUI and the override parser need to know of one parameter."""

    path: str
    name: str
    kind: type
    default: Any
    lo: float | None
    hi: float | None
    unit: str
    doc: str
    choices: tuple[str, ...] | None
    log_scale: bool


def _fmt(value: Any) -> str:
    return repr(value) if isinstance(value, str) else str(value)


def _range_text(meta: Mapping[str, Any]) -> str:
    lo, hi, unit = meta.get("lo"), meta.get("hi"), meta.get("unit") or ""
    left = "(" if meta.get("lo_open") else "["
    lo_s = "-inf" if lo is None else _fmt(lo)
    hi_s = "inf" if hi is None else _fmt(hi)
    return f"{left}{lo_s}, {hi_s}]" + (f" {unit}" if unit else "")


def _resolved_hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


@dataclass(frozen=True)
class StageConfig:
    """Base of every stage's parameters.

    Subclasses are frozen dataclasses; fields are declared with :func:`param` or :func:`nested`.
    Override :meth:`check` for rules that involve several fields (raise :class:`ConfigError`).
    """

    _path: ClassVar[str] = ""

    def __post_init__(self) -> None:
        hints = _resolved_hints(type(self))
        for f in fields(self):
            value = getattr(self, f.name)
            if f.metadata.get("nested"):
                if not isinstance(value, StageConfig):
                    raise ConfigError(f"{f.name}: expected a table of parameters, got {value!r}")
                continue
            coerced = _coerce(f.name, value, hints[f.name], f.metadata)
            if coerced is not value:
                object.__setattr__(self, f.name, coerced)
        self.check()

    def check(self) -> None:
        """Cross-field rules; raise :class:`ConfigError` naming the fields."""

    # ----- dict / TOML -------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, where: str = "") -> Self:
        """Build from a (possibly partial) mapping; unknown keys raise :class:`ConfigError`."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"{where or cls.__name__}: expected a table, got {data!r}")
        known = {f.name: f for f in fields(cls)}
        kwargs: dict[str, Any] = {}
        hints = _resolved_hints(cls)
        for key, value in data.items():
            name = f"{where}.{key}" if where else key
            if key not in known:
                allowed = ", ".join(sorted(known))
                raise ConfigError(f"{name}: unknown key (allowed: {allowed})")
            f = known[key]
            if f.metadata.get("nested"):
                kwargs[key] = hints[key].from_dict(value, where=name)
            else:
                kwargs[key] = value
        try:
            return cls(**kwargs)
        except ConfigError as err:
            if where and not str(err).startswith(where):
                raise ConfigError(f"{where}.{err}") from None
            raise

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (tuples as lists), TOML-serialisable."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, StageConfig):
                out[f.name] = value.to_dict()
            elif isinstance(value, tuple):
                out[f.name] = list(value)
            else:
                out[f.name] = value
        return out

    @classmethod
    def load(cls, path: str | Path) -> Self:
        """Read from a TOML file; errors name the file and the field."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise ConfigError(f"{path}: no such file") from None
        except tomllib.TOMLDecodeError as err:
            raise ConfigError(f"{path}: not valid TOML ({err})") from None
        try:
            return cls.from_dict(data)
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from None

    def save(self, path: str | Path) -> None:
        """Write as TOML."""
        Path(path).write_text(tomli_w.dumps(self.to_dict()))

    # ----- overrides ---------------------------------------------------------------------------
    def replace_path(self, dotted: str, value: Any) -> Self:
        """A copy with the parameter at ``dotted`` (``"voxel.voxel_size_m"``) set to ``value``."""
        head, _, rest = dotted.partition(".")
        known = {f.name: f for f in fields(self)}
        if head not in known:
            allowed = ", ".join(sorted(known))
            raise ConfigError(f"{dotted}: unknown key '{head}' (allowed: {allowed})")
        f = known[head]
        if f.metadata.get("nested"):
            if not rest:
                raise ConfigError(f"{dotted}: is a table; name one of its keys")
            try:
                sub = getattr(self, head).replace_path(rest, value)
            except ConfigError as err:
                msg = str(err)
                raise ConfigError(msg if msg.startswith(head + ".") else f"{head}.{msg}") from None
            # A rule spanning several tables is this level's own check(): its message already
            # names the fields from here, so it is not prefixed with the sub-table.
            return dataclasses.replace(self, **{head: sub})
        if rest:
            raise ConfigError(f"{dotted}: '{head}' is a parameter, not a table")
        return dataclasses.replace(self, **{head: value})

    def with_overrides(self, overrides: Mapping[str, Any]) -> Self:
        """Apply several ``dotted -> value`` overrides in order."""
        cfg = self
        for key, value in overrides.items():
            cfg = cfg.replace_path(key, value)
        return cfg

    def get_path(self, dotted: str) -> Any:
        """The value at ``dotted``."""
        obj: Any = self
        for part in dotted.split("."):
            if not isinstance(obj, StageConfig) or part not in {f.name for f in fields(obj)}:
                raise ConfigError(f"{dotted}: unknown key '{part}'")
            obj = getattr(obj, part)
        return obj

    # ----- introspection for the GUI -------------------------------------------------------------
    @classmethod
    def params(cls, prefix: str = "") -> Iterator[ParamInfo]:
        """Every leaf parameter with its range, unit and doc (depth first, declaration order)."""
        hints = _resolved_hints(cls)
        for f in fields(cls):
            path = f"{prefix}.{f.name}" if prefix else f.name
            if f.metadata.get("nested"):
                yield from hints[f.name].params(path)
                continue
            if not f.metadata.get("gui", True):
                continue
            default = f.default if f.default is not _MISSING else None
            yield ParamInfo(
                path=path,
                name=f.name,
                kind=_base_kind(hints[f.name]),
                default=default,
                lo=f.metadata.get("lo"),
                hi=f.metadata.get("hi"),
                unit=f.metadata.get("unit", ""),
                doc=f.metadata.get("doc", ""),
                choices=f.metadata.get("choices"),
                log_scale=bool(f.metadata.get("log_scale")),
            )


def _base_kind(hint: Any) -> type:
    origin = typing.get_origin(hint)
    if origin is tuple:
        return tuple
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return _base_kind(args[0])
    return hint if isinstance(hint, type) else object


def _check_number(name: str, value: float, meta: Mapping[str, Any]) -> None:
    if not math.isfinite(value):
        raise ConfigError(f"{name} = {value}: must be finite")
    lo, hi = meta.get("lo"), meta.get("hi")
    below = lo is not None and (value <= lo if meta.get("lo_open") else value < lo)
    above = hi is not None and value > hi
    if below or above:
        raise ConfigError(f"{name} = {_fmt(value)}: must be in {_range_text(meta)}")


def _coerce(name: str, value: Any, hint: Any, meta: Mapping[str, Any]) -> Any:
    kind = _base_kind(hint)
    optional = typing.get_origin(hint) in (typing.Union, types.UnionType) and type(None) in (
        typing.get_args(hint)
    )
    if value is None:
        if optional:
            return value
        raise ConfigError(f"{name}: a value is required")
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{name} = {_fmt(value)}: expected true or false")
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int | float) or int(value) != value:
            raise ConfigError(f"{name} = {_fmt(value)}: expected an integer")
        value = int(value)
        _check_number(name, value, meta)
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{name} = {_fmt(value)}: expected a number")
        value = float(value)
        _check_number(name, value, meta)
        return value
    if kind is str:
        if not isinstance(value, str):
            raise ConfigError(f"{name} = {_fmt(value)}: expected a string")
        choices = meta.get("choices")
        if choices and value not in choices:
            raise ConfigError(f"{name} = {value!r}: must be one of {', '.join(choices)}")
        return value
    if kind is tuple:
        if isinstance(value, str) or not isinstance(value, list | tuple):
            raise ConfigError(f"{name} = {_fmt(value)}: expected a list of numbers")
        out = []
        for i, item in enumerate(value):
            if isinstance(item, bool) or not isinstance(item, int | float):
                raise ConfigError(f"{name}[{i}] = {_fmt(item)}: expected a number")
            _check_number(f"{name}[{i}]", float(item), meta)
            out.append(float(item))
        return tuple(out)
    return value


def parse_override(text: str) -> tuple[str, Any]:
    """Parse one ``section.key=value`` override; the value is read as a TOML literal.

    ``voxel.voxel_size_m=0.005`` gives ``("voxel.voxel_size_m", 0.005)``; a bare word that is not
    a TOML literal (``method=paper``) is taken as a string.
    """
    key, sep, raw = text.partition("=")
    key, raw = key.strip(), raw.strip()
    if not sep or not key or not raw:
        raise ConfigError(f"--set {text!r}: expected section.key=value")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return key, value
