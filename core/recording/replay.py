"""Re-run perception and fusion on recorded camera frames and compare with what was recorded.

Pure: the reader's output in (:class:`~.frames.CapturedFrame` s in recording order, the recorded
estimates by ``(camera, seq)``), results out. Each camera's frames go, in order, through a fresh
:class:`~hapticloud.core.perception.CameraPipeline` of its own: its ICP memory evolves frame after
frame as it did while recording, so with the recording's own parameters the estimates come out
bit for bit the same. The fusion is re-run twice with the same parameters, once on the recorded
estimates and once on the new ones (each fed at its capture time and sampled there), so the
fused difference says what the parameter change does to the surface the tick would see.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import ConfigError
from ..fusion import FusionConfig, SurfaceFusion
from ..perception import CameraPipeline, PerceptionConfig, SurfaceEstimate
from .frames import CapturedFrame, roi_covers

FloatArray = NDArray[np.float64]

#: How far a recorded unit normal may be from the re-run's and count as the same (a few ulps of
#: 1.0: what normalising it again can change).
NORMAL_ULPS = 4 * float(np.finfo(np.float64).eps)


@dataclass(frozen=True)
class ReplayRow:
    """One frame: the recorded estimate (``None`` if the recording has none) and the new one."""

    camera: str
    seq: int
    t: float
    recorded: SurfaceEstimate | None
    new: SurfaceEstimate
    #: The new parameters' crop reads pixels outside the stored rectangle (the re-run saw less).
    roi_exceeded: bool
    recorded_fused: FloatArray | None = None
    new_fused: FloatArray | None = None

    @property
    def centroid_diff_m(self) -> float:
        """Distance between the recorded and the new centroid where both are valid, else NaN."""
        if self.recorded is None or not (self.recorded.valid and self.new.valid):
            return math.nan
        return float(np.linalg.norm(self.new.centroid - self.recorded.centroid))

    @property
    def normal_diff_deg(self) -> float:
        if self.recorded is None or not (self.recorded.valid and self.new.valid):
            return math.nan
        cos = float(np.clip(self.new.normal @ self.recorded.normal, -1.0, 1.0))
        return math.degrees(math.acos(cos))

    @property
    def identical(self) -> bool:
        """The new estimate says exactly what the recorded one said (validity, point, normal)."""
        rec = self.recorded
        if rec is None:
            return False
        # Bit for bit, but for the normal's last bits: every rebuild of an estimate (the
        # session's re-stamp, the wire form's decoding) normalises the unit normal again, which
        # can move it by an ulp.
        return (
            rec.valid == self.new.valid
            and bool(np.array_equal(rec.centroid, self.new.centroid))
            and bool(np.all(np.abs(rec.normal - self.new.normal) <= NORMAL_ULPS))
        )


@dataclass(frozen=True)
class ReplayResult:
    """Every replayed frame and the comparison's figures (see :meth:`summary`)."""

    rows: tuple[ReplayRow, ...]
    perception: PerceptionConfig
    fusion: FusionConfig
    per_camera: Mapping[str, int] = field(default_factory=dict)

    def summary(self) -> dict[str, object]:
        """JSON-ready figures: frames, exact matches, validity changes, largest differences."""
        rows = self.rows
        diffs = np.array([r.centroid_diff_m for r in rows], dtype=np.float64)
        ndiffs = np.array([r.normal_diff_deg for r in rows], dtype=np.float64)
        both = np.isfinite(diffs)
        fused = [
            float(np.linalg.norm(r.new_fused - r.recorded_fused))
            for r in rows
            if r.new_fused is not None and r.recorded_fused is not None
        ]
        compared = [r for r in rows if r.recorded is not None]
        return {
            "frames": len(rows),
            "frames_per_camera": dict(self.per_camera),
            "with_recorded_estimate": len(compared),
            "identical": sum(r.identical for r in compared),
            "both_valid": int(both.sum()),
            "valid_recorded_only": sum(
                bool(r.recorded.valid and not r.new.valid) for r in compared
            ),
            "valid_new_only": sum(bool(r.new.valid and not r.recorded.valid) for r in compared),
            "roi_exceeded": sum(r.roi_exceeded for r in rows),
            "max_centroid_diff_mm": float(diffs[both].max() * 1e3) if both.any() else None,
            "median_centroid_diff_mm": float(np.median(diffs[both]) * 1e3) if both.any() else None,
            "max_normal_diff_deg": float(ndiffs[both].max()) if both.any() else None,
            "max_fused_diff_mm": max(fused) * 1e3 if fused else None,
        }


def replay(
    frames: Iterable[CapturedFrame],
    recorded: Mapping[tuple[str, int], SurfaceEstimate],
    perception: PerceptionConfig,
    fusion: FusionConfig | None = None,
    progress: Callable[[int], None] | None = None,
    on_row: Callable[[ReplayRow], None] | None = None,
) -> ReplayResult:
    """Re-run perception (and fusion) on ``frames``; see the module docstring.

    Parameters
    ----------
    frames
        Recorded frames in recording order (each camera's in its capture order).
    recorded
        The recorded estimates by ``(camera, seq)`` (a frame without one is replayed, not
        compared).
    perception, fusion
        The parameters of the re-run (the recording's own, or changed).
    progress
        Called with the number of frames done, every 100 frames.
    on_row
        Called with each row as soon as it is made (a GUI draws the re-run as it goes).
    """
    fusion_cfg = FusionConfig() if fusion is None else fusion
    pipes: dict[str, CameraPipeline] = {}
    fused_old, fused_new = SurfaceFusion(fusion_cfg), SurfaceFusion(fusion_cfg)
    rows: list[ReplayRow] = []
    counts: dict[str, int] = {}
    for i, cap in enumerate(frames):
        name = cap.camera
        pipe = pipes.get(name)
        if pipe is None:
            pipe = pipes[name] = CameraPipeline(perception, camera=name)
        new = pipe.process_depth(cap.frame, cap.hip, exclude=cap.exclude)
        old = recorded.get((name, cap.seq))
        t = cap.frame.t
        row = ReplayRow(
            camera=name,
            seq=cap.seq,
            t=t,
            recorded=old,
            new=new,
            roi_exceeded=not roi_covers(cap.frame, cap.hip, perception.crop, cap.roi),
            recorded_fused=_fuse(fused_old, old, t) if old is not None else None,
            new_fused=_fuse(fused_new, new, t),
        )
        rows.append(row)
        if on_row is not None:
            on_row(row)
        counts[name] = counts.get(name, 0) + 1
        if progress is not None and (i + 1) % 100 == 0:
            progress(i + 1)
    return ReplayResult(tuple(rows), perception, fusion_cfg, counts)


def _fuse(fusion: SurfaceFusion, est: SurfaceEstimate, t: float) -> FloatArray | None:
    """Feed one estimate (re-timed to the capture time) and sample the fused centroid there."""
    if est.t != t:
        # The recorded estimate may carry another clock (run --hardware: monotonic); the
        # comparison puts both on the frame's.
        est = dataclasses.replace(est, t=t)
    fusion.add(est)
    fusion.prepare()
    surface = fusion.sample(t)
    return np.array(surface.centroid) if surface.valid else None


def _merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _tail(text: str) -> str:
    """What a config error says after the field it names (``"x.y = 1: must be ..."``)."""
    return text.split(": ", 1)[1] if ": " in text else text


def replay_configs(
    recorded: Mapping[str, str],
    preset: Mapping[str, Any] | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> tuple[PerceptionConfig, FusionConfig]:
    """The re-run's parameters: the recording's (``perception``/``fusion`` TOML texts), then a
    preset's ``[perception]``/``[fusion]`` tables, then ``--set`` overrides
    (``perception.voxel.voxel_size_m = 0.004``). ``ConfigError`` names what is wrong."""
    tables: dict[str, dict[str, Any]] = {}
    for name in ("perception", "fusion"):
        try:
            tables[name] = tomllib.loads(recorded.get(name, ""))
        except tomllib.TOMLDecodeError as err:
            raise ConfigError(f"recorded {name} parameters: not valid TOML ({err})") from None
    for name, table in (preset or {}).items():
        if name not in tables:
            raise ConfigError(
                f"--preset [{name}]: replay re-runs perception and fusion only "
                "(tables [perception] and [fusion])"
            )
        if not isinstance(table, Mapping):
            raise ConfigError(f"--preset {name}: expected a table")
        tables[name] = _merge(tables[name], table)
    perception = PerceptionConfig.from_dict(tables["perception"], where="perception")
    fusion = FusionConfig.from_dict(tables["fusion"], where="fusion")
    for key, value in (overrides or {}).items():
        head, _, rest = key.partition(".")
        try:
            if head == "perception" and rest:
                perception = perception.replace_path(rest, value)
                continue
            if head == "fusion" and rest:
                fusion = fusion.replace_path(rest, value)
                continue
        except ConfigError as err:
            raise ConfigError(f"--set {key} = {value!r}: {_tail(str(err))}") from None
        raise ConfigError(
            f"--set {key}: replay re-runs perception and fusion only (perception.* or fusion.*)"
        )
    return perception, fusion


__all__ = ["ReplayResult", "ReplayRow", "replay", "replay_configs"]
