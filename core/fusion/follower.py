"""PID followers that move the output toward the regression's target each control tick.

Law (per scalar channel, ``e = target - y``, derivative on the measurement ``y``, not on ``e``, so
a target that jumps when a new estimate arrives gives no derivative kick)::

    w' = kp e + ki ∫e dt - kd w          y' = w

It is integrated with backward Euler (closed form below): unconditionally stable for every
``dt > 0`` whenever the continuous law is (Routh–Hurwitz, checked by the config), so there is no
``dt``-dependent gain limit. On top of it, each tick:

* the step is clamped into ``[0, e]``: the output never passes the target (then ``w`` is set to
  the step actually taken and the integral is frozen: back-calculation anti-windup);
* ``|ki ∫e|`` is clamped to a configured acceleration (integral clamp);
* a speed / turn-rate limit bounds the total change per tick.

A feed-forward (the regression's own motion between ticks) is applied before the PID, so a surface
moving along the fitted polynomial is followed without lag and the PID only smooths the jumps the
target makes when a refit arrives. The normal follower does the same on the sphere: a scalar PID
on the angle to the target, the output rotated by the PID's angle about ``output × target`` (so it
stays unit whatever the gains).
"""

from __future__ import annotations

import math
from typing import NamedTuple

from .regression import Vec3, perpendicular


class PidGains(NamedTuple):
    """Gains of one follower: ``kp`` 1/s², ``ki`` 1/s³, ``kd`` 1/s; ``i_limit`` bounds |∫e dt|."""

    kp: float
    ki: float
    kd: float
    i_limit: float

    @classmethod
    def make(cls, kp: float, ki: float, kd: float, i_accel_limit: float) -> PidGains:
        """Gains with the integral clamped so that ``|ki ∫e| <= i_accel_limit``."""
        return cls(kp, ki, kd, i_accel_limit / ki if ki > 0.0 else 0.0)


def pid_step(
    e: float, w: float, integ: float, dt: float, g: PidGains
) -> tuple[float, float, float]:
    """One backward-Euler tick of the scalar law with the error ``e`` before the step.

    Returns ``(step, w, integral)``; ``step`` lies in ``[min(0, e), max(0, e)]`` and ``dt <= 0``
    changes nothing.
    """
    if not dt > 0.0:
        return 0.0, w, integ
    kp, ki, kd, i_limit = g
    # Implicit in w', e' = e - dt w' and ∫' = ∫ + dt e': solved for w' in closed form; the
    # denominator is >= 1 for non-negative gains, so no division can blow up.
    w_new = (w + dt * ((kp + ki * dt) * e + ki * integ)) / (1.0 + dt * (kd + dt * (kp + dt * ki)))
    step = w_new * dt
    lo, hi = (0.0, e) if e >= 0.0 else (e, 0.0)
    if step > hi or step < lo:
        step = hi if step > hi else lo
        return step, step / dt, integ
    integ += dt * (e - step)
    if integ > i_limit:
        integ = i_limit
    elif integ < -i_limit:
        integ = -i_limit
    return step, w_new, integ


def iteration_matrix(g: PidGains, dt: float) -> list[list[float]]:
    """The linear map of one unclamped tick on ``(e, w, ∫e)`` for a fixed target.

    Backward Euler is A-stable: for gains passing Routh–Hurwitz the spectral radius is < 1 for
    every ``dt > 0`` (the tests check it; a GUI can show it as the follower's stability margin).
    """
    kp, ki, kd, _ = g
    den = 1.0 + dt * (kd + dt * (kp + dt * ki))
    w_row = [dt * (kp + ki * dt) / den, 1.0 / den, dt * ki / den]
    e_row = [1.0 - dt * w_row[0], -dt * w_row[1], -dt * w_row[2]]
    i_row = [dt * e_row[0], dt * e_row[1], 1.0 + dt * e_row[2]]
    return [e_row, w_row, i_row]


class PointFollower:
    """Follows a 3D target (the centroid, m) with one PID per coordinate."""

    __slots__ = ("gains", "initialised", "integ", "w", "y")

    def __init__(self, gains: PidGains) -> None:
        self.gains = gains
        self.y: list[float] = [0.0, 0.0, 0.0]
        self.w: list[float] = [0.0, 0.0, 0.0]
        self.integ: list[float] = [0.0, 0.0, 0.0]
        self.initialised = False

    def reset(self, value: Vec3 | None = None) -> None:
        """Restart at ``value`` at rest (or forget the state when ``None``)."""
        self.initialised = value is not None
        if value is not None:
            self.y = [value[0], value[1], value[2]]
        self.w = [0.0, 0.0, 0.0]
        self.integ = [0.0, 0.0, 0.0]

    def step(
        self, target: Vec3, dt: float, ff: Vec3 = (0.0, 0.0, 0.0), max_step: float = math.inf
    ) -> Vec3:
        """Advance by the feed-forward ``ff`` (m), then the PID toward ``target``; returns ``y``.

        The total displacement is at most ``max_step`` (m); ``dt <= 0`` leaves the state as is.
        """
        y = self.y
        if not dt > 0.0:
            return (y[0], y[1], y[2])
        g, w, integ = self.gains, self.w, self.integ
        new = [0.0, 0.0, 0.0]
        for i in range(3):
            base = y[i] + ff[i]
            s, w[i], integ[i] = pid_step(target[i] - base, w[i], integ[i], dt, g)
            new[i] = base + s
        dx, dy, dz = new[0] - y[0], new[1] - y[1], new[2] - y[2]
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        if dist > max_step:
            f = max_step / dist
            new = [y[0] + dx * f, y[1] + dy * f, y[2] + dz * f]
            w[0], w[1], w[2] = w[0] * f, w[1] * f, w[2] * f
        self.y = new
        return (new[0], new[1], new[2])


def rotate(v: Vec3, axis: Vec3, angle: float) -> Vec3:
    """``v`` rotated by ``angle`` (rad) about unit ``axis`` (Rodrigues)."""
    kx, ky, kz = axis
    vx, vy, vz = v
    c, s = math.cos(angle), math.sin(angle)
    d = (kx * vx + ky * vy + kz * vz) * (1.0 - c)
    return (
        vx * c + (ky * vz - kz * vy) * s + kx * d,
        vy * c + (kz * vx - kx * vz) * s + ky * d,
        vz * c + (kx * vy - ky * vx) * s + kz * d,
    )


def toward(a: Vec3, b: Vec3) -> tuple[float, Vec3]:
    """Angle (rad) from unit ``a`` to unit ``b`` and the unit tangent at ``a`` pointing to ``b``.

    At ``b == a`` the tangent is arbitrary (angle 0); at ``b == -a`` a fixed perpendicular.
    """
    c = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    ux, uy, uz = b[0] - c * a[0], b[1] - c * a[1], b[2] - c * a[2]
    s = math.sqrt(ux * ux + uy * uy + uz * uz)
    if s < 1e-15:
        return (0.0 if c > 0.0 else math.pi), perpendicular(a)
    return math.atan2(s, c), (ux / s, uy / s, uz / s)


def _unit(v: Vec3) -> Vec3:
    n = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return (v[0] / n, v[1] / n, v[2] / n)


class NormalFollower:
    """Follows a unit target normal on the sphere with a PID on the angle to the target."""

    __slots__ = ("gains", "initialised", "integ", "n", "w")

    def __init__(self, gains: PidGains) -> None:
        self.gains = gains
        self.n: Vec3 = (0.0, 0.0, 1.0)
        self.w = 0.0
        self.integ = 0.0
        self.initialised = False

    def reset(self, value: Vec3 | None = None) -> None:
        """Restart at unit ``value`` at rest (or forget the state when ``None``)."""
        self.initialised = value is not None
        if value is not None:
            self.n = value
        self.w = 0.0
        self.integ = 0.0

    def step(
        self,
        target: Vec3,
        dt: float,
        ff_from: Vec3 | None = None,
        ff_gain: float = 1.0,
        max_angle: float = math.pi,
    ) -> Vec3:
        """Rotate by ``ff_gain`` times the rotation ``ff_from -> target`` (feed-forward), then by
        the PID's angle toward ``target``; the total turn is at most ``max_angle`` (rad)."""
        n0 = self.n
        if not dt > 0.0:
            return n0
        n = n0
        if ff_from is not None and ff_gain > 0.0:
            ang, _ = toward(ff_from, target)
            if ang > 0.0:
                k = (
                    ff_from[1] * target[2] - ff_from[2] * target[1],
                    ff_from[2] * target[0] - ff_from[0] * target[2],
                    ff_from[0] * target[1] - ff_from[1] * target[0],
                )
                kn = math.sqrt(k[0] * k[0] + k[1] * k[1] + k[2] * k[2])
                if kn > 1e-15:
                    n = rotate(n, (k[0] / kn, k[1] / kn, k[2] / kn), ff_gain * ang)
        err, u = toward(n, target)
        s, self.w, self.integ = pid_step(err, self.w, self.integ, dt, self.gains)
        if s != 0.0:
            c, si = math.cos(s), math.sin(s)
            n = (n[0] * c + u[0] * si, n[1] * c + u[1] * si, n[2] * c + u[2] * si)
        total, u0 = toward(n0, n)
        if total > max_angle:
            c, si = math.cos(max_angle), math.sin(max_angle)
            n = (n0[0] * c + u0[0] * si, n0[1] * c + u0[1] * si, n0[2] * c + u0[2] * si)
            self.w *= max_angle / total
        self.n = n = _unit(n)
        return n
