"""Force constraint: the force the robot would press into the surface stays under ISO/TS 15066.

The paper names a force constraint without defining it; this is the definition used here.

Model. Treat the surface as a rigid, frictionless, still contact at the HIP along ``n``. With the
contact force ``lam * n`` on the robot (``lam >= 0`` pushes the HIP out of the surface), the
equation of motion ``M qdd + nle = tau + J_c^T lam`` (``nle``: Coriolis, centrifugal and gravity
torques) and the contact condition ``J_c qdd + Jdc_qd = 0`` give the force the actuators press
with::

    lam(tau) = -Lambda_c (J_c M^-1 (tau - nle) + Jdc_qd),    Lambda_c = 1 / (J_c M^-1 J_c^T)

``Lambda_c`` is the robot's effective mass along ``n`` at the HIP. The constraint is
``lam(tau) <= F_lim`` with ``F_lim = safety_factor * ISO limit(body region)``. Multiplied by
``mu_c = J_c M^-1 J_c^T = 1 / Lambda_c`` it is a row of ``G x <= h`` over ``x = [qdd; tau]`` in
m/s^2 (the free acceleration the torques would give along ``-n``, bounded by ``F_lim / Lambda_c``)::

    G = [0, -J_c M^-1]        h = mu_c F_lim - J_c M^-1 nle + Jdc_qd

Why this form: it never inverts ``mu_c``, which goes to zero when the arm cannot move the HIP
along ``n`` (a singular direction, where a tiny torque makes a huge contact force): the row then
tends to ``0 <= Jdc_qd`` instead of blowing up, and in between it allows only the small torques
that are safe there. ``M`` is positive definite on this robot, so ``M^-1 J_c^T`` is one well
conditioned 6x6 solve.

Assumptions: rigid contact (the patient's tissue is softer: the real force builds up more slowly,
so the bound is conservative in time); the patient's own muscle force and the surface's
acceleration are not included; only pressing (``lam > 0``) is bounded, pulling away is free. The
row acts on ``tau`` alone, so it holds whatever the hierarchy does with ``qdd``; under the
contact-free equation of motion (``tau - nle = M qdd``) it reads ``-Lambda_c (J_c qdd + Jdc_qd) <=
F_lim``. It is only active within ``activation_distance_m`` of contact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import lapack

from ..config import StageConfig, param
from ..control.rows import Inequality, empty_inequality
from ..errors import InputError
from ..validation import as_unit_vector3
from .distance import HapticState, HipState, check_dt, haptic_state
from .iso15066 import CONTACT_TYPES, REGION_KEYS, BodyRegion, body_region

FloatArray = NDArray[np.float64]

#: ``mu_c`` (1/kg) below this is treated as a singular direction when reporting a force.
MU_SINGULAR = 1.0e-9


@dataclass(frozen=True)
class ForceConstraintConfig(StageConfig):
    """Parameters of :class:`ForceConstraint`."""

    _path: ClassVar[str] = "haptics.force"

    contact: str = param(
        "quasi_static",
        choices=CONTACT_TYPES,
        doc="ISO/TS 15066 contact type whose force limit applies",
    )
    safety_factor: float = param(
        0.5,
        lo=0.0,
        lo_open=True,
        hi=1.0,
        doc="fraction of the ISO limit the robot may press with (patients, model errors)",
    )
    default_body_region: str = param(
        "face",
        choices=REGION_KEYS,
        doc="region used when the surface names none (face is the strictest)",
    )
    contact_area_m2: float = param(
        0.0,
        lo=0.0,
        hi=0.01,
        unit="m^2",
        doc="if > 0, also limit the force to the region's pressure times this area",
    )
    activation_distance_m: float = param(
        0.01, lo=0.0, hi=1.0, unit="m", doc="no rows while d_proj is above this distance"
    )


def mass_factor(mass_matrix: FloatArray, name: str = "hip.mass_matrix") -> FloatArray:
    """The upper Cholesky factor of the mass matrix (float64, ``(n, n)``), for :func:`solve_mass`.

    LAPACK directly: ~2 us for 6x6 against ~12-15 us through numpy's checked solve, and its
    failure is the positive-definiteness check.

    Raises
    ------
    InputError
        If the matrix is not symmetric positive definite (named by ``name``).
    """
    factor, info = lapack.dpotrf(mass_matrix, lower=False)
    if info != 0:
        raise InputError(f"{name}: must be symmetric positive definite")
    return factor


def solve_mass(factor: FloatArray, J_c: FloatArray) -> tuple[FloatArray, float]:
    """``w = M^-1 J_c^T`` and ``mu_c = J_c M^-1 J_c^T`` (1/kg) from :func:`mass_factor`'s factor."""
    w, _ = lapack.dpotrs(factor, J_c, lower=False)
    return w, float(J_c.dot(w))


def _mass_terms(state: HipState, n: int) -> tuple[FloatArray, FloatArray]:
    """The checked factor of the state's mass matrix, and its nonlinear effects."""
    M = np.asarray(state.mass_matrix, dtype=np.float64)
    nle = np.asarray(state.nonlinear_effects, dtype=np.float64)
    if M.shape != (n, n) or not np.isfinite(M).all():
        raise InputError(f"hip.mass_matrix: expected a finite ({n}, {n}) matrix, got {M.shape}")
    if nle.shape != (n,) or not np.isfinite(nle).all():
        raise InputError(f"hip.nonlinear_effects: expected {n} finite numbers, got {nle.shape}")
    return mass_factor(M), nle


def effective_mass_kg(state: HipState, normal: ArrayLike) -> float:
    """The robot's effective mass along ``normal`` at the HIP, ``(n^T J M^-1 J^T n)^-1`` (kg).

    ``inf`` in a singular direction (the arm cannot move the HIP along ``normal``).
    """
    n = as_unit_vector3(normal, "normal")
    J_c = n @ np.asarray(state.jacobian, dtype=np.float64)
    factor, _ = _mass_terms(state, J_c.shape[0])
    _, mu = solve_mass(factor, J_c)
    return math.inf if mu <= MU_SINGULAR else 1.0 / mu


class ForceConstraint:
    """Force haptic constraint: one inequality row on ``tau`` when the HIP is at the surface.

    Parameters
    ----------
    config
        Contact type, safety factor, default region; defaults if omitted.
    name
        Name given to the rows.
    """

    default_name: ClassVar[str] = "haptic_force"

    def __init__(
        self, config: ForceConstraintConfig | None = None, name: str = default_name
    ) -> None:
        self.config = config or ForceConstraintConfig()
        self.name = name
        self._limit_by_name: dict[str, float] = {}

    def region_of(self, surface: Any) -> BodyRegion:
        """The ISO region of ``surface`` (its ``body_region``, else the configured default).

        Raises
        ------
        ConfigError
            If the surface names a region that ISO/TS 15066 does not have.
        """
        name = getattr(surface, "body_region", "") or self.config.default_body_region
        return body_region(name)

    def force_limit_n(self, surface: Any) -> float:
        """``F_lim`` (N): the safety factor times the ISO limit of the surface's body region."""
        name = getattr(surface, "body_region", "") or self.config.default_body_region
        limit = self._limit_by_name.get(name)
        if limit is None:  # the config is frozen, so a region's limit never changes
            cfg = self.config
            region = body_region(name)
            limit = cfg.safety_factor * region.force_limit_n(cfg.contact, cfg.contact_area_m2)
            self._limit_by_name[name] = limit
        return limit

    def rows(
        self, state: HipState, surface: Any, dt: float, *, haptic: HapticState | None = None
    ) -> Inequality:
        """The constraint's rows for this tick.

        Parameters
        ----------
        state
            Robot-side HIP quantities of this tick (uses ``mass_matrix`` and
            ``nonlinear_effects``).
        surface
            :class:`~.distance.SurfacePoint` or any object with ``centroid``, ``normal``
            (optionally ``body_region``).
        dt
            Control period (s); checked for a uniform interface, not used by the row.
        haptic
            ``haptic_state(state, surface)`` if the caller has it already; ``state`` still
            supplies the mass matrix and the nonlinear effects, ``surface`` the body region.

        Returns
        -------
        Inequality
            One row ``G x <= h`` (m/s^2) acting on the ``tau`` part of ``x = [qdd; tau]``, or no
            rows if the surface is farther than ``activation_distance_m``.

        Raises
        ------
        ConfigError
            If the surface names an unknown body region.
        """
        check_dt(dt)
        limit = self.force_limit_n(surface)
        hs = haptic if haptic is not None else haptic_state(state, surface)
        n = hs.n_joints
        if hs.d_proj > self.config.activation_distance_m:
            return empty_inequality(2 * n, self.name)
        factor, nle = _mass_terms(state, n)
        w, bound = self.bound(hs, factor, nle, limit)
        G = np.zeros((1, 2 * n))
        G[0, n:] = -w
        return Inequality(G, np.array([bound]), self.name)

    @staticmethod
    def bound(
        hs: HapticState, factor: FloatArray, nonlinear_effects: FloatArray, limit_n: float
    ) -> tuple[FloatArray, float]:
        """``(w, h)`` of the row ``G = [0, -w^T]``, ``h = mu_c F_lim - w . nle + Jdc_qd``, with
        ``w = M^-1 J_c^T`` (``factor``: :func:`mass_factor`'s).

        The constraint's one formula: :meth:`rows` and the haptic loop's rows both call it (the
        loop factors ``M`` once per tick for every surface).
        """
        w, mu = solve_mass(factor, hs.J_c)
        return w, mu * limit_n - float(w.dot(nonlinear_effects)) + hs.Jdc_qd


def contact_force_n(state: HipState, surface: Any, tau: ArrayLike) -> float:
    """The force ``lam`` (N) the torques ``tau`` would press into a rigid still surface.

    Positive = pressing into the surface. For monitoring and plots; in a singular direction
    (``mu_c`` below :data:`MU_SINGULAR`) the effective mass is capped at ``1 / MU_SINGULAR`` so
    the value stays finite.
    """
    hs = haptic_state(state, surface)
    t = np.asarray(tau, dtype=np.float64)
    if t.shape != (hs.n_joints,) or not np.isfinite(t).all():
        raise InputError(f"tau: expected {hs.n_joints} finite numbers, got shape {t.shape}")
    factor, nle = _mass_terms(state, hs.n_joints)
    w, mu = solve_mass(factor, hs.J_c)
    return -(float(w @ (t - nle)) + hs.Jdc_qd) / max(mu, MU_SINGULAR)
