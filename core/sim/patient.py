"""The simulated patient's arm: a scripted intent pulling the handle through a spring-damper.

The patient's hand holds the handle. The hand's mass ``m`` moves with the HIP; the muscles are a
spring-damper (``k``, ``c``) between the HIP and the intent trajectory ``x_i(t)``, so the force
on the hand is::

    F = k (x_i - x_hip) + c (v_i - v_hip)

The handle's force sensor measures what the hand passes on to the handle,
``F_hand = F - m a_hip`` (the hand's own inertia is carried by the sensor too). The arm's
posture in the null space of the HIP Jacobian is held by a weak joint-space spring-damper
towards the initial posture, as a relaxed arm would (the exoskeleton's cuffs transmit it; the
handle's sensor does not see it): without it the redundant joints would drift under a force acting
at the HIP alone.

The intent is a list of waypoints joined by straight segments, each with its own time law:
``"linear"`` (constant speed: a direct impact at a set speed) or ``"min_jerk"`` (a smooth
reaching movement). The intent holds the first waypoint before its time and the last after, or,
with a repeat period, plays the waypoints again every period (a demo that goes on).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..validation import as_finite_scalar, as_vector3

FloatArray = NDArray[np.float64]

PROFILES = ("linear", "min_jerk")
#: A repeated intent's last waypoint must be this close to its first (m): the same point.
_RETURN_TOLERANCE_M = 1e-6


class Waypoint(NamedTuple):
    """Arrive at ``position`` (m, world) at time ``t_s`` (s) following ``profile``."""

    t_s: float
    position: FloatArray
    profile: str = "min_jerk"


def _min_jerk(s: float) -> tuple[float, float]:
    """Minimum-jerk time law: position fraction and its derivative in ``s`` (both in [0, 1])."""
    s2 = s * s
    return s2 * s * (10.0 - 15.0 * s + 6.0 * s2), 30.0 * s2 * (1.0 - s) * (1.0 - s)


class IntentScript:
    """The patient's intended hand (HIP) trajectory, piecewise along straight segments.

    Parameters
    ----------
    waypoints
        At least one; times strictly increasing (s), positions in m.
    repeat_s, repeat_name
        0: play once. Otherwise the waypoints play again every ``repeat_s`` seconds from the first
        one's time; the period must cover them and the last must return to the first position
        (the intent never jumps). ``repeat_name`` names it in errors.

    Examples
    --------
    >>> script = IntentScript([Waypoint(0.0, np.zeros(3)), Waypoint(1.0, np.array([0.5, 0, 0]),
    ...                                                              "linear")])
    >>> script.position(0.5).tolist(), script.velocity(0.5).tolist()
    ([0.25, 0.0, 0.0], [0.5, 0.0, 0.0])
    """

    def __init__(
        self, waypoints: Sequence[Waypoint], repeat_s: float = 0.0, repeat_name: str = "repeat_s"
    ) -> None:
        if not waypoints:
            raise InputError("waypoints: the intent needs at least one waypoint")
        times, points, profiles = [], [], []
        for i, wp in enumerate(waypoints):
            t = as_finite_scalar(wp.t_s, f"waypoints[{i}].t_s")
            if times and not t > times[-1]:
                raise InputError(
                    f"waypoints[{i}].t_s = {t}: must be after the previous waypoint ({times[-1]})"
                )
            if wp.profile not in PROFILES:
                raise InputError(
                    f"waypoints[{i}].profile = {wp.profile!r}: must be one of {', '.join(PROFILES)}"
                )
            times.append(t)
            points.append(as_vector3(wp.position, f"waypoints[{i}].position"))
            profiles.append(wp.profile)
        self.times = np.array(times)
        self.points = np.array(points)
        self.profiles = tuple(profiles)
        self.repeat_s = as_finite_scalar(repeat_s, repeat_name)
        if self.repeat_s < 0.0:
            raise InputError(f"{repeat_name} = {self.repeat_s}: must be 0 (once) or a period (s)")
        if self.repeat_s > 0.0:
            span = times[-1] - times[0]
            if self.repeat_s < span:
                raise InputError(
                    f"{repeat_name} = {self.repeat_s:g}: shorter than the waypoints it repeats "
                    f"({span:g} s)"
                )
            gap = float(np.linalg.norm(self.points[-1] - self.points[0]))
            if gap > _RETURN_TOLERANCE_M:
                raise InputError(
                    f"{repeat_name} = {self.repeat_s:g}: the last waypoint is {gap * 1e3:.1f} mm "
                    "from the first; a repeated intent must return to where it starts"
                )

    @property
    def end_s(self) -> float:
        """Time of the last waypoint (s)."""
        return float(self.times[-1])

    def _segment(self, t: float) -> tuple[int, float, float]:
        """Segment index ``i`` (from waypoint i-1 to i), fraction and d(fraction)/dt at ``t``."""
        times = self.times
        if self.repeat_s > 0.0 and times[0] < t < math.inf:
            t = float(times[0]) + math.fmod(t - float(times[0]), self.repeat_s)
        if t <= times[0] or times.shape[0] == 1:
            return 0, 1.0, 0.0
        if t >= times[-1]:
            return times.shape[0] - 1, 1.0, 0.0
        i = int(np.searchsorted(times, t, side="right"))
        duration = times[i] - times[i - 1]
        s = (t - times[i - 1]) / duration
        if self.profiles[i] == "linear":
            return i, s, 1.0 / duration
        frac, rate = _min_jerk(s)
        return i, frac, rate / duration

    def position(self, t: float) -> FloatArray:
        """Intended HIP position (m) at time ``t`` (s)."""
        i, frac, _ = self._segment(t)
        if i == 0:
            return self.points[0].copy()
        return self.points[i - 1] + frac * (self.points[i] - self.points[i - 1])

    def velocity(self, t: float) -> FloatArray:
        """Intended HIP velocity (m/s) at time ``t`` (s)."""
        i, _, rate = self._segment(t)
        if i == 0 or rate == 0.0:
            return np.zeros(3)
        return rate * (self.points[i] - self.points[i - 1])


class PatientArm:
    """The patient's arm as it acts on the exoskeleton (see the module docstring).

    Parameters
    ----------
    intent
        The intended HIP trajectory.
    mass_kg
        Effective mass of the hand and forearm at the handle (kg), moving with the HIP.
    stiffness_n_per_m, damping_n_s_per_m
        Muscle spring-damper between the HIP and the intent.
    posture
        Joint posture (rad) the relaxed arm holds in the Jacobian's null space.
    posture_stiffness_nm_per_rad, posture_damping_nms_per_rad
        Null-space joint spring-damper towards ``posture``.
    """

    def __init__(
        self,
        intent: IntentScript,
        *,
        mass_kg: float,
        stiffness_n_per_m: float,
        damping_n_s_per_m: float,
        posture: ArrayLike,
        posture_stiffness_nm_per_rad: float = 2.0,
        posture_damping_nms_per_rad: float = 0.5,
    ) -> None:
        self.intent = intent
        self.mass_kg = _non_negative(mass_kg, "mass_kg")
        self.stiffness = _non_negative(stiffness_n_per_m, "stiffness_n_per_m")
        self.damping = _non_negative(damping_n_s_per_m, "damping_n_s_per_m")
        self.posture = np.array(posture, dtype=np.float64).reshape(-1)
        if not np.isfinite(self.posture).all():
            raise InputError("posture: must be finite")
        self.k_posture = _non_negative(posture_stiffness_nm_per_rad, "posture_stiffness")
        self.d_posture = _non_negative(posture_damping_nms_per_rad, "posture_damping")
        self._projection: tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None = None

    def hand_force(self, t: float, hip: FloatArray, hip_velocity: FloatArray) -> FloatArray:
        """Muscle force on the hand (N, world) at time ``t`` for the HIP state given."""
        intent = self.intent
        return self.stiffness * (intent.position(t) - hip) + self.damping * (
            intent.velocity(t) - hip_velocity
        )

    def forces(
        self,
        t: float,
        hip: FloatArray,
        hip_velocity: FloatArray,
        q: FloatArray,
        qd: FloatArray,
        jacobian: FloatArray,
        inertia: FloatArray,
    ) -> tuple[FloatArray, FloatArray]:
        """What the arm does to the exoskeleton at ``t``: the hand force (N, world) and the
        posture torque (N m); the signature of :meth:`~hapticloud.core.sim.exo.ExoPlant.step`'s
        force callback."""
        return self.hand_force(t, hip, hip_velocity), self.posture_torque(q, qd, jacobian, inertia)

    def posture_torque(
        self, q: FloatArray, qd: FloatArray, jacobian: FloatArray, inertia: FloatArray
    ) -> FloatArray:
        """Null-space joint torque (N m) holding the arm's posture.

        Projected with the dynamically consistent null space of the HIP Jacobian
        (``N^T = I - J^T (J M^-1 J^T)^-1 J M^-1``), so it turns the redundant joints without
        accelerating the HIP: the hand's motion is the muscle force's alone.
        """
        if self.k_posture == 0.0 and self.d_posture == 0.0:
            return np.zeros_like(q)
        tau = self.k_posture * (self.posture - q) - self.d_posture * qd
        cached = self._projection
        if cached is not None and cached[0] is jacobian and cached[1] is inertia:
            minv_jt, lam = cached[2], cached[3]  # the same configuration terms (frozen_dynamics)
        else:
            minv_jt = np.linalg.solve(inertia, jacobian.T)
            lam = np.linalg.pinv(jacobian @ minv_jt, rcond=1e-9)  # task-space inertia, guarded
            # Only read-only arrays are remembered (an array changed in place would leave a
            # stale projection); held by reference, so their ids cannot be reused meanwhile.
            frozen = not (jacobian.flags.writeable or inertia.flags.writeable)
            self._projection = (jacobian, inertia, minv_jt, lam) if frozen else None
        return tau - jacobian.T @ (lam @ (minv_jt.T @ tau))


def _non_negative(value: float, name: str) -> float:
    out = as_finite_scalar(value, name)
    if out < 0.0:
        raise InputError(f"{name} = {out}: must be >= 0")
    return out


def segment_time(a: ArrayLike, b: ArrayLike, speed_mps: float, profile: str) -> float:
    """Duration (s) of a segment from ``a`` to ``b`` travelled at ``speed_mps`` (peak speed for
    ``linear``; for ``min_jerk`` the average speed, whose peak is 1.875 times higher)."""
    speed = as_finite_scalar(speed_mps, "speed_mps")
    if not speed > 0.0:
        raise InputError(f"speed_mps = {speed}: must be positive")
    length = float(np.linalg.norm(as_vector3(b, "b") - as_vector3(a, "a")))
    if profile not in PROFILES:
        raise InputError(f"profile = {profile!r}: must be one of {', '.join(PROFILES)}")
    return max(length / speed, 1e-3) if math.isfinite(length) else 1e-3


__all__ = ["PROFILES", "IntentScript", "PatientArm", "Waypoint", "segment_time"]
