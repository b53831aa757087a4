"""What cannot be seen is not free space: the surface guard of the haptic tick.

The fused surface is the tick's only knowledge of the patient. When it is valid and its newest
estimate at most ``fresh_s`` old, the constraints act on it (``KNOWN``); a camera's fresh proof
that its whole workspace is empty (see :func:`free_proof_holds`) is knowledge too: ``KNOWN`` with
no surface. Otherwise (no estimate yet, an invalid, stale or old one, a watchdog that distrusts
the cameras) the space around the HIP is *unknown*, and unknown is treated as near:

``HOLDING``
    the last known surface stays a hard constraint. It keeps moving with its last velocity and
    is grown towards the HIP by a margin that grows with the age of the newest estimate beyond
    ``fresh_s`` and with the surface's speed when last seen fresh (``margin = (age - fresh_s) *
    (growth_m_s + speed_factor * |v|)``): the patient may have moved toward the hand, unseen.
    The approach speed toward it is capped at ``approach_m_s``, and, farther from it than
    ``lateral_beyond_m``, the HIP's speed along it at ``lateral_m_s``: a held plane says nothing
    of what lies beside it (another body may be just out of the old estimate's view), so the
    hand may not cross unseen space fast while the surface is held. In contact the hand slides
    on the surface it holds, frictionless as when the surface is known.
``STOPPED``
    the newest estimate is ``stop_after_s`` old, or no surface was ever known: the robot comes
    to rest and holds the joint position where it stopped (a joint-space PD task at level 5),
    still kept out of the (frozen) held surface by level 4.

``KNOWN`` returns as soon as the fused surface is valid again. Every change is a frozen
:class:`SpaceTransition` with its reason, kept for the app and the report.

Pure logic: explicit times, no clock, no threads (the same object runs in the simulator and in the
real-time control process).
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..config import StageConfig, param
from .distance import SurfacePoint

FloatArray = NDArray[np.float64]

_ZERO3 = np.zeros(3)
_ZERO3.setflags(write=False)


class SpaceState(enum.IntEnum):
    """What the tick knows of the space around the HIP (the code is the report's integer)."""

    KNOWN = 0
    HOLDING = 1
    STOPPED = 2

    @property
    def label(self) -> str:
        return self.name.lower()


@dataclass(frozen=True)
class UnknownSpaceConfig(StageConfig):
    """How the tick treats space it cannot see (scene table ``haptics.unknown``)."""

    _path: ClassVar[str] = "haptics.unknown"

    fresh_s: float = param(
        0.1,
        lo=0.0,
        hi=1.0,
        unit="s",
        doc="the fused surface is known while its newest estimate is at most this old",
    )
    stop_after_s: float = param(
        0.3,
        lo=0.0,
        hi=5.0,
        unit="s",
        doc="newest estimate this old (or none): stop and hold position (0: stop at once)",
    )
    approach_m_s: float = param(
        0.05, lo=0.0, hi=1.0, unit="m/s", doc="approach speed cap toward the held surface"
    )
    lateral_m_s: float = param(
        0.05,
        lo=0.0,
        hi=1.0,
        unit="m/s",
        doc="speed cap along the held surface (what lies beside a held plane is unseen)",
    )
    lateral_beyond_m: float = param(
        0.02,
        lo=0.0,
        hi=0.5,
        unit="m",
        doc="the speed cap applies this far from the held surface and beyond (in contact the "
        "hand slides on the surface it holds)",
    )
    growth_m_s: float = param(
        0.1,
        lo=0.0,
        hi=2.0,
        unit="m/s",
        doc="the held surface grows toward the HIP this fast (unseen motion of the patient)",
    )
    speed_factor: float = param(
        1.0,
        lo=0.0,
        hi=5.0,
        doc="extra growth per m/s of the surface's speed when last seen fresh",
    )
    hold_kp: float = param(
        400.0, lo=0.0, hi=1e5, unit="1/s²", doc="stiffness of the position hold (per joint)"
    )
    hold_kd: float = param(
        40.0, lo=0.0, hi=1e3, unit="1/s", doc="damping of the position hold (per joint)"
    )
    min_free_m: float = param(
        0.03,
        lo=0.0,
        hi=0.5,
        unit="m",
        doc="an empty-workspace proof counts while the HIP sphere stays this far inside it",
    )
    log_size: int = param(256, lo=8, hi=100_000, gui=False, doc="transitions kept")


class SpaceTransition(NamedTuple):
    """One change of :class:`SpaceState` at time ``t`` (s), with its reason."""

    t: float
    state: SpaceState
    reason: str


class GuardDecision(NamedTuple):
    """What the tick acts on: the surface (or ``None``), the approach cap and the stop target.

    ``approach_limit_mps`` is ``None`` where the guard adds no cap; ``hold_q`` is the joint
    position to hold while ``STOPPED`` (``None`` otherwise).
    """

    state: SpaceState
    surface: SurfacePoint | None
    approach_limit_mps: float | None
    hold_q: FloatArray | None


class SurfaceGuard:
    """Decides each tick between the fused surface, a held surface and a stop (see module doc)."""

    def __init__(self, config: UnknownSpaceConfig | None = None) -> None:
        self.config = config if config is not None else UnknownSpaceConfig()
        self._log: deque[SpaceTransition] = deque(maxlen=self.config.log_size)
        self.reset()

    def reset(self) -> None:
        """Forget every surface: the next tick without a valid one stops."""
        self._state = SpaceState.STOPPED
        self._reason = "no surface known yet"
        self._last: SurfacePoint | None = None
        self._last_t = -math.inf
        self._last_age = 0.0
        # The surface's speed when last seen fresh: an old fused surface is held still by the
        # fusion (its velocity zero past max_extrapolation_s) while the body may still move.
        self._fresh_speed = 0.0
        self._frozen: SurfacePoint | None = None
        self._hold_q: FloatArray | None = None
        self._entered = False

    def configure(self, config: UnknownSpaceConfig) -> None:
        """Use ``config`` from the next tick on (state kept)."""
        self.config = config

    @property
    def state(self) -> SpaceState:
        return self._state

    @property
    def reason(self) -> str:
        """Why the space is in its state (empty while ``KNOWN``)."""
        return self._reason

    @property
    def transitions(self) -> tuple[SpaceTransition, ...]:
        """Every change of state, oldest first (bounded to ``log_size``)."""
        return tuple(self._log)

    def unknown_for_s(self, t: float) -> float:
        """Age of the newest estimate behind the surface (s; inf if none)."""
        return self._age(t)

    def _age(self, t: float) -> float:
        return (t - self._last_t) + self._last_age if self._last is not None else math.inf

    def step(
        self,
        t: float,
        known: SurfacePoint | None,
        q: FloatArray,
        reason: str = "",
        free: bool = False,
        age_s: float = 0.0,
    ) -> GuardDecision:
        """One tick at time ``t``: ``known`` is the valid fused surface and ``age_s`` the age of
        the newest estimate behind it, or ``None`` with ``reason`` saying why there is none;
        ``free`` that the space is proven empty instead (:func:`free_proof_holds`); ``q`` the
        measured joint positions.

        A surface older than ``fresh_s`` is held (grown by its age beyond ``fresh_s``, approach
        capped) even while the fusion still calls it valid; the stop comes when the newest
        estimate is ``stop_after_s`` old.
        """
        cfg = self.config
        if known is not None and not age_s < math.inf:  # NaN or inf: no age, no knowledge
            known, reason = None, reason or f"surface of unknown age ({age_s})"
        if known is not None:
            self._last, self._last_t = known, t
            self._last_age = age_s if age_s > 0.0 else 0.0
            self._frozen = None  # a newer surface to hold (frozen again if stopped)
            if self._last_age <= cfg.fresh_s:
                v = np.asarray(known.velocity, dtype=np.float64)
                self._fresh_speed = math.sqrt(float(v.dot(v)))
                self._hold_q = None
                self._enter(t, SpaceState.KNOWN, "")
                return GuardDecision(SpaceState.KNOWN, known, None, None)
            reason = f"newest estimate {self._last_age * 1e3:.0f} ms old"
        elif free:
            # Nothing near: no surface to hold if the proof lapses (stop at once then).
            self._last, self._last_t, self._last_age, self._fresh_speed = None, t, 0.0, 0.0
            self._frozen, self._hold_q = None, None
            self._enter(t, SpaceState.KNOWN, "")
            return GuardDecision(SpaceState.KNOWN, None, None, None)
        reason = reason or "no valid surface estimate"
        if self._last is None or self._age(t) >= cfg.stop_after_s:
            return self._stopped(t, q, reason)
        self._hold_q = None
        self._enter(t, SpaceState.HOLDING, reason)
        return GuardDecision(SpaceState.HOLDING, self._grown(t), cfg.approach_m_s, None)

    def _stopped(self, t: float, q: FloatArray, reason: str) -> GuardDecision:
        if self._hold_q is None:  # the position where it stopped, kept while stopped
            self._hold_q = np.array(q, dtype=np.float64)
        if self._frozen is None and self._last is not None:
            self._frozen = self._grown(t, still=True)
        if self._state is not SpaceState.STOPPED or not self._entered:
            why = (
                f"{reason}; no surface known yet"
                if self._last is None
                else f"{reason}; newest estimate {self._age(t):.3f} s old"
            )
            self._enter(t, SpaceState.STOPPED, why)
        return GuardDecision(SpaceState.STOPPED, self._frozen, 0.0, self._hold_q)

    def _grown(self, t: float, still: bool = False) -> SurfacePoint:
        """The last known surface moved on with its velocity and grown toward the HIP by its
        estimate's age beyond ``fresh_s``."""
        last = self._last
        assert last is not None
        cfg = self.config
        since = max(0.0, t - self._last_t)
        unseen = max(0.0, self._age(t) - cfg.fresh_s)
        v = np.asarray(last.velocity, dtype=np.float64)
        speed = max(math.sqrt(float(v.dot(v))), self._fresh_speed)
        growth = cfg.growth_m_s + cfg.speed_factor * speed
        n = np.asarray(last.normal, dtype=np.float64)
        centroid = np.asarray(last.centroid, dtype=np.float64) + since * v + (unseen * growth) * n
        velocity = _ZERO3 if still else v + growth * n
        return SurfacePoint(centroid, n, velocity, last.body_region)

    def _enter(self, t: float, state: SpaceState, reason: str) -> None:
        if state is self._state and self._entered:
            return
        self._state, self._reason, self._entered = state, reason, True
        self._log.append(SpaceTransition(t, state, reason))


def free_proof_holds(
    free_m: float,
    free_hip: FloatArray | None,
    hip: FloatArray,
    hip_radius_m: float,
    config: UnknownSpaceConfig,
) -> bool:
    """Whether an empty-workspace proof (no surface within ``free_m`` of ``free_hip``) still
    covers the HIP sphere at ``hip`` with ``min_free_m`` to spare (the HIP moved since)."""
    if not free_m > 0.0 or free_hip is None:
        return False
    d = hip - free_hip
    moved = math.sqrt(float(d.dot(d)))
    return free_m - moved - hip_radius_m >= config.min_free_m


def hold_acceleration(
    q: FloatArray, qd: FloatArray, hold_q: FloatArray, config: UnknownSpaceConfig
) -> FloatArray:
    """Joint accelerations of the position hold: ``-kp (q - q_hold) - kd qd`` (rad/s²)."""
    return -config.hold_kp * (q - hold_q) - config.hold_kd * qd


__all__: list[Any] = [
    "GuardDecision",
    "SpaceState",
    "SpaceTransition",
    "SurfaceGuard",
    "UnknownSpaceConfig",
    "free_proof_holds",
    "hold_acceleration",
]
