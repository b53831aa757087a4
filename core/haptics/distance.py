"""Haptic quantities shared by the constraints: the free distance ``d_proj`` and its Jacobian.

Sign conventions (paper eqs. 7-8, world frame, SI units):

- the surface normal ``n`` is a unit vector pointing out of the surface, **towards the HIP**;
- ``d_proj = (c - h) . (-n) - r_hip = (h - c) . n - r_hip`` is the signed free distance (m):
  positive = free space between the HIP sphere and the surface, negative = penetration;
- ``J_c = n^T J_trans`` (1 x n, m/rad), so ``d_dot = J_c qd`` for a still surface: **a negative
  d_dot approaches the surface**;
- ``Jdc_qd = n^T (Jdot qd)`` (m/s^2), so ``d_ddot = J_c qdd + Jdc_qd``. The normal's own rate
  ``n_dot`` is neglected, as in the paper: the term ``(h - c) . n_dot`` vanishes when ``c`` is the
  closest point (then ``h - c`` is parallel to ``n`` and ``n_dot`` is perpendicular to ``n``), and
  the term ``2 (h_dot - c_dot) . n_dot`` of ``d_ddot`` is dropped because the fused normal turns
  slowly (its follower filters it harder than the centroid).

A surface moving with velocity ``v_s`` changes the distance by ``d_dot_surface = -n . v_s``
(negative when the surface comes towards the HIP). The constraints decide whether to use it.

The robot side (:class:`HipState`) is computed once per tick and shared by every constraint and
every surface (the live surface and each static virtual wall); :func:`haptic_state` combines it
with one surface into the few numbers a constraint needs (:class:`HapticState`).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..validation import as_finite_scalar, as_unit_vector3, as_vector3

FloatArray = NDArray[np.float64]

_ZERO3 = np.zeros(3)
_ZERO3.setflags(write=False)


class SurfacePoint(NamedTuple):
    """The surface a constraint acts on, at this tick (world frame).

    Any object with ``centroid`` and ``normal`` attributes works where a surface is expected
    (e.g. the fusion's ``FusedSurface``); ``velocity`` and ``body_region`` are optional there.

    Attributes
    ----------
    centroid
        Closest surface point ``c`` (m), shape (3,).
    normal
        Unit normal ``n`` out of the surface towards the HIP, shape (3,) (normalised on use).
    velocity
        Velocity of the surface point ``c`` (m/s), shape (3,); zero for a static wall.
    body_region
        ISO/TS 15066 body region the surface belongs to (see :mod:`.iso15066`); ``""`` = unknown.
    """

    centroid: FloatArray
    normal: FloatArray
    velocity: FloatArray = _ZERO3
    body_region: str = ""


class RobotStateSource(Protocol):
    """What :meth:`HipState.from_model` reads (a :class:`~hapticloud.core.robot.RobotModel`)."""

    @property
    def qd(self) -> FloatArray: ...

    def hip_position(self) -> FloatArray: ...

    def hip_jacobian(self) -> FloatArray: ...

    def hip_jdot_qd(self) -> FloatArray: ...

    def mass_matrix(self) -> FloatArray: ...

    def nonlinear_effects(self) -> FloatArray: ...


class HipState(NamedTuple):
    """Robot-side quantities at the HIP for one tick (surface independent).

    Attributes
    ----------
    position
        HIP centre ``h`` (m), shape (3,).
    qd
        Joint velocities (rad/s), shape (n,).
    jacobian
        Translational HIP Jacobian in world axes (m/rad), shape (3, n).
    jdot_qd
        ``Jdot qd`` (m/s^2), shape (3,).
    mass_matrix
        ``M(q)`` (kg m^2), shape (n, n), symmetric positive definite (force constraint only).
    nonlinear_effects
        ``h(q, qd)`` (N m), shape (n,) (force constraint only).
    radius_m
        HIP radius ``r_hip`` (m): the safety offset around the HIP (paper: 0.04 m).
    """

    position: FloatArray
    qd: FloatArray
    jacobian: FloatArray
    jdot_qd: FloatArray
    mass_matrix: FloatArray
    nonlinear_effects: FloatArray
    radius_m: float

    @property
    def n_joints(self) -> int:
        """Number of joints ``n`` (the decision vector ``[qdd; tau]`` has ``2 n`` entries)."""
        return int(self.qd.shape[0])

    @classmethod
    def from_model(cls, model: RobotStateSource, radius_m: float) -> HipState:
        """Read the HIP quantities of a model after its ``update(q, qd)``.

        Raises
        ------
        InputError
            If ``radius_m`` is negative or not finite.
        """
        radius = as_finite_scalar(radius_m, "radius_m")
        if radius < 0.0:
            raise InputError(f"radius_m = {radius}: must be >= 0")
        return cls(
            model.hip_position(),
            model.qd,
            model.hip_jacobian(),
            model.hip_jdot_qd(),
            model.mass_matrix(),
            model.nonlinear_effects(),
            radius,
        )


class HapticState(NamedTuple):
    """One surface seen from the HIP: what the positional and velocity constraints need.

    Attributes
    ----------
    d_proj
        Signed free distance (m), negative = penetration.
    J_c
        Constraint Jacobian ``n^T J_trans`` (m/rad), shape (n,).
    Jdc_qd
        ``n^T Jdot qd`` (m/s^2).
    d_dot_robot
        ``J_c qd`` (m/s): the distance rate the robot's own motion causes.
    d_dot_surface
        ``-n . v_s`` (m/s): the distance rate the surface's motion causes.
    qd
        Joint velocities (rad/s), shape (n,).
    normal
        Unit normal ``n``, shape (3,).
    surface_velocity
        ``v_s`` (m/s), shape (3,).
    """

    d_proj: float
    J_c: FloatArray
    Jdc_qd: float
    d_dot_robot: float
    d_dot_surface: float
    qd: FloatArray
    normal: FloatArray
    surface_velocity: FloatArray

    @property
    def n_joints(self) -> int:
        """Number of joints ``n``."""
        return int(self.J_c.shape[0])

    def distance_rate(self, surface_feedforward: bool) -> float:
        """``d_dot`` (m/s): the robot's own rate, plus the surface's with the feed-forward (the
        HIP's rate relative to a moving surface); negative = approaching."""
        return self.d_dot_robot + (self.d_dot_surface if surface_feedforward else 0.0)


def d_proj(centroid: ArrayLike, normal: ArrayLike, hip: ArrayLike, r_hip_m: float) -> float:
    """Signed free distance ``(c - h) . (-n) - r_hip`` (m), paper eq. 7.

    Parameters
    ----------
    centroid
        Closest surface point ``c`` (m), shape (3,).
    normal
        Surface normal ``n`` towards the HIP, shape (3,); normalised here.
    hip
        HIP centre ``h`` (m), shape (3,).
    r_hip_m
        HIP radius (m), >= 0.

    Returns
    -------
    float
        Positive = free distance between HIP sphere and surface, negative = penetration depth.
    """
    c = as_vector3(centroid, "centroid")
    n = as_unit_vector3(normal, "normal")
    h = as_vector3(hip, "hip")
    r = as_finite_scalar(r_hip_m, "r_hip_m")
    if r < 0.0:
        raise InputError(f"r_hip_m = {r}: must be >= 0")
    return trusted_d_proj(c, n, h, r)


def trusted_d_proj(
    centroid: FloatArray, normal: FloatArray, hip: FloatArray, r_hip_m: float
) -> float:
    """The formula of :func:`d_proj`, ``(h - c) . n - r_hip`` (m), without any check.

    For float arrays of shape (3,) with a unit ``normal`` already known (a fused surface's, the
    loop's): the checks of :func:`d_proj` cost ~20 µs a call, which at 800 Hz is 2 % of a core.
    """
    return float((hip - centroid).dot(normal)) - r_hip_m


def constraint_jacobian(normal: ArrayLike, jacobian: ArrayLike) -> FloatArray:
    """``J_c = n^T J_trans`` (m/rad), shape (n,), paper eq. 8.

    Parameters
    ----------
    normal
        Surface normal towards the HIP, shape (3,); normalised here.
    jacobian
        Translational HIP Jacobian in world axes (m/rad), shape (3, n).
    """
    n = as_unit_vector3(normal, "normal")
    jac = _as_jacobian(jacobian)
    return n @ jac


def _as_jacobian(jacobian: ArrayLike) -> FloatArray:
    jac = np.asarray(jacobian, dtype=np.float64)
    if jac.ndim != 2 or jac.shape[0] != 3 or jac.shape[1] == 0:
        raise InputError(f"jacobian: expected shape (3, n), got {np.shape(jacobian)}")
    if not np.isfinite(jac).all():
        raise InputError("jacobian: must be finite")
    return jac


def surface_of(surface: Any) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(centroid, unit normal, velocity)`` of any surface-like object, validated.

    Raises
    ------
    InputError
        If the centroid, normal or velocity is not a finite 3-vector, or the normal is ~zero.
    """
    centroid, normal, velocity = _surface_fields(surface)
    c = as_vector3(centroid, "surface.centroid")
    n = as_unit_vector3(normal, "surface.normal")
    v = _ZERO3 if velocity is None else as_vector3(velocity, "surface.velocity")
    return c, n, v


def _surface_fields(surface: Any) -> tuple[Any, Any, Any]:
    try:
        centroid, normal = surface.centroid, surface.normal
    except AttributeError:
        raise InputError(
            f"surface: expected an object with centroid and normal, got {type(surface).__name__}"
        ) from None
    return centroid, normal, getattr(surface, "velocity", None)


def _array(value: Any) -> FloatArray | None:
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None


def _validate_slowly(hip: HipState, surface: Any) -> None:
    """Name the argument that is wrong (the fast path only knows that something is)."""
    surface_of(surface)
    as_vector3(hip.position, "hip.position")
    as_vector3(hip.jdot_qd, "hip.jdot_qd")
    jac = _as_jacobian(hip.jacobian)
    qd = _array(hip.qd)
    if qd is None or qd.shape != (jac.shape[1],) or not np.isfinite(qd).all():
        raise InputError(f"hip.qd: expected {jac.shape[1]} finite numbers, got {hip.qd!r}")
    radius = as_finite_scalar(hip.radius_m, "hip.radius_m")
    if radius < 0.0:
        raise InputError(f"hip.radius_m = {radius}: must be >= 0")


def haptic_state(hip: HipState, surface: Any) -> HapticState:
    """Combine the robot's HIP state with one surface (see the module docstring for signs).

    Parameters
    ----------
    hip
        Robot-side quantities of this tick.
    surface
        A :class:`SurfacePoint` or any object with ``centroid``, ``normal`` (and optionally
        ``velocity``).

    Raises
    ------
    InputError
        If a vector has the wrong shape or is not finite (names it).
    """
    # Runs several times per 800 Hz tick: one cheap check of all shapes and of all numbers
    # together; only when that fails is the culprit searched for, to name it.
    centroid, normal, velocity = _surface_fields(surface)
    c, n, h = _array(centroid), _array(normal), _array(hip.position)
    v = _ZERO3 if velocity is None else _array(velocity)
    jac, qd, jdot_qd = _array(hip.jacobian), _array(hip.qd), _array(hip.jdot_qd)
    try:
        radius = float(hip.radius_m)
    except (TypeError, ValueError):
        radius = math.nan
    shapes_ok = (
        c is not None
        and n is not None
        and h is not None
        and v is not None
        and jac is not None
        and qd is not None
        and jdot_qd is not None
        and c.shape == n.shape == h.shape == v.shape == jdot_qd.shape == (3,)
        and jac.ndim == 2
        and jac.shape[0] == 3
        and jac.shape[1] > 0
        and qd.shape == (jac.shape[1],)
    )
    if not shapes_ok or not 0.0 <= radius < math.inf:
        _validate_slowly(hip, surface)
        raise InputError("haptic_state: inputs of inconsistent shapes")
    if not np.isfinite(np.concatenate((c, n, h, v, jdot_qd, qd, jac.ravel()))).all():
        _validate_slowly(hip, surface)
        raise InputError("haptic_state: every input must be finite")
    length = math.sqrt(float(n @ n))
    if not 1e-12 < length < math.inf:
        _validate_slowly(hip, surface)
        raise InputError("surface.normal: must be a finite non-zero direction")
    n = n / length
    trusted = HipState(h, qd, jac, jdot_qd, hip.mass_matrix, hip.nonlinear_effects, radius)
    state = trusted_haptic_state(trusted, SurfacePoint(c, n, v))
    # Finite inputs can still overflow (|x| ~ 1e154); J_c reaches the total through d_dot_robot.
    total = state.d_proj + state.Jdc_qd + state.d_dot_robot + state.d_dot_surface
    if not math.isfinite(total):
        raise InputError("haptic_state: inputs too large, the distance or its rates overflow")
    return state


def trusted_haptic_state(hip: HipState, surface: SurfacePoint) -> HapticState:
    """The formulas of :func:`haptic_state` (eqs. 7-8 and the rates), without any check.

    For inputs already known to be float arrays of the right shapes with a unit normal (the
    haptic loop's: the robot model checks ``q`` and ``qd``, the fusion and the walls hand out
    finite unit normals): the checks cost ~10 µs per surface at 800 Hz. A non-finite result is
    the caller's to detect (then :func:`haptic_state` names the culprit).
    """
    n = surface.normal
    J_c = n.dot(hip.jacobian)
    return HapticState(
        trusted_d_proj(surface.centroid, n, hip.position, hip.radius_m),
        J_c,
        float(n.dot(hip.jdot_qd)),
        float(J_c.dot(hip.qd)),
        -float(n.dot(surface.velocity)),
        hip.qd,
        n,
        surface.velocity,
    )


DT_MIN_S = 1.0e-6
DT_MAX_S = 1.0


def check_dt(dt: float) -> float:
    """``dt`` (s) as a float in ``[1e-6, 1]`` s, or :class:`InputError` naming ``dt``.

    The bounds keep ``1/dt^2`` and the rows finite; a control period outside them is a bug.
    """
    value = as_finite_scalar(dt, "dt")
    if not DT_MIN_S <= value <= DT_MAX_S:
        raise InputError(f"dt = {value}: must be in [{DT_MIN_S}, {DT_MAX_S}] s")
    return value
