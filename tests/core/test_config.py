"""The parameter machinery: validation on construction, TOML round trips, overrides."""

from __future__ import annotations

from dataclasses import FrozenInstanceError, dataclass

import pytest
from hapticloud.core.config import StageConfig, nested, param, parse_override
from hapticloud.core.errors import ConfigError
from hypothesis import given
from hypothesis import strategies as st


@dataclass(frozen=True)
class RingConfig(StageConfig):
    r_in_m: float = param(0.02, lo=0.0, lo_open=True, hi=1.0, unit="m", doc="inner radius")
    r_out_m: float = param(0.1, lo=0.0, lo_open=True, hi=1.0, unit="m", doc="outer radius")
    iterations: int = param(5, lo=1, hi=50, doc="ICP iterations")
    enabled: bool = param(True, doc="use the memory")
    method: str = param("quadric", choices=("paper", "quadric"), doc="estimator")
    radii_m: tuple[float, ...] = param((0.03, 0.06), lo=0.0, hi=1.0, unit="m", doc="shells")

    def check(self) -> None:
        if not self.r_in_m < self.r_out_m:
            raise ConfigError(f"r_in_m = {self.r_in_m}: must be below r_out_m ({self.r_out_m})")


@dataclass(frozen=True)
class TopConfig(StageConfig):
    ring: RingConfig = nested(RingConfig)
    rate_hz: float = param(30.0, lo=1.0, hi=1000.0, unit="Hz")


def test_defaults_are_valid_and_frozen() -> None:
    cfg = TopConfig()
    assert cfg.ring.r_out_m == 0.1
    with pytest.raises(FrozenInstanceError):
        cfg.rate_hz = 5.0  # type: ignore[misc]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"r_in_m": 0.0}, "r_in_m = 0.0: must be in (0.0, 1.0] m"),
        ({"r_out_m": 2.0}, "r_out_m = 2.0: must be in (0.0, 1.0] m"),
        ({"r_in_m": 0.2, "r_out_m": 0.1}, "r_in_m = 0.2: must be below r_out_m (0.1)"),
        ({"iterations": 2.5}, "iterations = 2.5: expected an integer"),
        ({"iterations": True}, "iterations = True: expected an integer"),
        ({"enabled": 1}, "enabled = 1: expected true or false"),
        ({"method": "x"}, "method = 'x': must be one of paper, quadric"),
        ({"radii_m": (0.1, -1)}, "radii_m[1] = -1.0: must be in [0.0, 1.0] m"),
        ({"r_in_m": float("nan")}, "r_in_m = nan: must be finite"),
        ({"r_in_m": "a"}, "r_in_m = 'a': expected a number"),
    ],
)
def test_invalid_values_name_field_and_range(kwargs: dict, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        RingConfig(**kwargs)
    assert str(err.value) == message


def test_toml_round_trip(tmp_path) -> None:
    cfg = TopConfig().with_overrides({"ring.r_in_m": 0.03, "ring.method": "paper", "rate_hz": 15})
    path = tmp_path / "p.toml"
    cfg.save(path)
    assert TopConfig.load(path) == cfg


def test_unknown_key_in_file_names_file_and_key(tmp_path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("[ring]\nr_inn_m = 0.01\n")
    with pytest.raises(ConfigError, match=r"bad.toml: ring.r_inn_m: unknown key"):
        TopConfig.load(path)


def test_nested_error_is_prefixed(tmp_path) -> None:
    with pytest.raises(ConfigError, match=r"^ring.r_in_m = 0.5: must be below"):
        TopConfig.from_dict({"ring": {"r_in_m": 0.5}})
    with pytest.raises(ConfigError, match=r"^ring.iterations = 0: must be in"):
        TopConfig().replace_path("ring.iterations", 0)


def test_missing_and_broken_files(tmp_path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        TopConfig.load(tmp_path / "nope.toml")
    (tmp_path / "x.toml").write_text("ring = [")
    with pytest.raises(ConfigError, match="not valid TOML"):
        TopConfig.load(tmp_path / "x.toml")


def test_parse_override() -> None:
    assert parse_override("ring.r_in_m=0.03") == ("ring.r_in_m", 0.03)
    assert parse_override("ring.method=paper") == ("ring.method", "paper")
    assert parse_override("ring.radii_m=[0.1, 0.2]") == ("ring.radii_m", [0.1, 0.2])
    assert parse_override("ring.enabled=false") == ("ring.enabled", False)
    with pytest.raises(ConfigError, match=r"expected section\.key=value"):
        parse_override("ring.r_in_m")


def test_params_expose_ranges_for_the_gui() -> None:
    infos = {p.path: p for p in TopConfig.params()}
    assert infos["ring.r_in_m"].unit == "m"
    assert infos["ring.iterations"].kind is int
    assert infos["ring.method"].choices == ("paper", "quadric")
    assert infos["rate_hz"].hi == 1000.0


@given(st.floats(allow_nan=True, allow_infinity=True))
def test_any_float_is_accepted_or_refused_cleanly(value: float) -> None:
    try:
        cfg = RingConfig(r_in_m=value)
    except ConfigError as err:
        assert str(err).startswith("r_in_m = ")
    else:
        assert 0.0 < cfg.r_in_m < cfg.r_out_m
