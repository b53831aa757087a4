"""The simulated exoskeleton: rigid-body dynamics with the patient's hand, integrated in substeps.

The plant is the URDF model (Pinocchio, through its own :class:`~hapticloud.core.robot.RobotModel`
instance, never the controller's) plus what the controller's model does not know: the patient's
hand mass ``m`` at the HIP and viscous joint friction ``b``::

    (M + m J^T J) qdd + h + m J^T (Jdot qd) + b qd = tau + J^T F + tau_posture

``F`` is the patient's muscle force on the hand and ``tau_posture`` the arm's null-space posture
torque (:mod:`.patient`). The hand's weight is carried by the patient (as a seated patient holds
their arm), so ``m`` adds inertia, not gravity. The handle's force sensor reads
``F_hand = F - m (J qdd + Jdot qd)``, what the hand passes to the handle; a controller that adds
``J^T F_hand`` to its equation of motion then has the plant's exact dynamics, one tick late.

Integration: semi-implicit (symplectic) Euler at ``substeps`` times the control rate with the
torque held (zero-order hold, as a drive does between commands). Joints stop at their position
limits (the velocity into the stop is removed: a hard, inelastic end stop).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..robot import RobotModel
from ..validation import as_finite_scalar, as_vector3

FloatArray = NDArray[np.float64]

#: ``(t, hip, hip_velocity, q, qd, J, inertia) -> (F on the hand (3,) N, joint torque (n,) N m)``;
#: ``inertia`` is the plant's joint-space inertia with the hand.
ForceModel = Callable[
    [float, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray],
    tuple[FloatArray, FloatArray],
]


class PlantState(NamedTuple):
    """The plant after a step: joint state, HIP state and what the sensor read (last substep)."""

    q: FloatArray
    qd: FloatArray
    hip: FloatArray
    hip_velocity: FloatArray
    hand_force: FloatArray
    muscle_force: FloatArray


class ExoPlant:
    """The exoskeleton with the patient's hand, advanced one control period at a time.

    Parameters
    ----------
    model
        A robot model used only by the plant.
    q0
        Initial joint positions (rad); the plant starts at rest.
    dt
        Control period (s).
    substeps
        Integration steps per control period.
    hand_mass_kg
        The patient's hand/forearm mass at the HIP (kg).
    joint_friction_nms_per_rad
        Viscous friction per joint (N m s/rad), unknown to the controller.
    frozen_dynamics
        Evaluate the robot's configuration terms (``M``, ``h``, ``J``, ``Jdot qd``) once per
        control period instead of at every substep, with the HIP moved by ``J dq`` within it.
        The patient's spring still acts at every substep (it is what needs them); the arm moves
        a few mrad in a period, so the terms change by a fraction of a percent. About half the
        cost of a period: for the real-time emulated arm, whose budget is one core's share with
        the app's cameras and view beside it. The deterministic simulation keeps the exact form.
    """

    def __init__(
        self,
        model: RobotModel,
        q0: ArrayLike,
        *,
        dt: float,
        substeps: int = 4,
        hand_mass_kg: float = 0.0,
        joint_friction_nms_per_rad: float = 0.0,
        frozen_dynamics: bool = False,
    ) -> None:
        self.model = model
        self.frozen_dynamics = bool(frozen_dynamics)
        n = model.n_joints
        q = np.array(q0, dtype=np.float64).reshape(-1)
        if q.shape != (n,) or not np.isfinite(q).all():
            raise InputError(f"q0: expected {n} finite joint positions, got {np.shape(q0)}")
        self.dt = as_finite_scalar(dt, "dt")
        if not self.dt > 0:
            raise InputError(f"dt = {self.dt}: must be positive")
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise InputError(f"substeps = {substeps!r}: expected a positive integer")
        self.substeps = substeps
        self.hand_mass_kg = as_finite_scalar(hand_mass_kg, "hand_mass_kg")
        self.friction = as_finite_scalar(joint_friction_nms_per_rad, "joint_friction")
        if self.hand_mass_kg < 0 or self.friction < 0:
            raise InputError("hand_mass_kg, joint_friction_nms_per_rad: must be >= 0")
        self.q = np.clip(q, model.q_min, model.q_max)
        self.qd = np.zeros(n)
        self.t = 0.0
        model.update(self.q, self.qd)
        self._hand_force = np.zeros(3)
        self._muscle = np.zeros(3)

    def state(self) -> PlantState:
        """The current state (HIP from the model's last update)."""
        m = self.model
        return PlantState(
            self.q.copy(),
            self.qd.copy(),
            m.hip_position().copy(),
            m.hip_velocity().copy(),
            self._hand_force.copy(),
            self._muscle.copy(),
        )

    def step(self, tau: ArrayLike, forces: ForceModel | None = None) -> PlantState:
        """Advance one control period with joint torques ``tau`` (N m) held.

        ``forces`` gives the patient's force on the hand and the posture torque at each substep.
        """
        tau = np.asarray(tau, dtype=np.float64)
        m = self.model
        n = m.n_joints
        if tau.shape != (n,) or not np.isfinite(tau).all():
            raise InputError(f"tau: expected {n} finite torques, got {tau!r}")
        if self.frozen_dynamics:
            return self._step_frozen(tau, forces)
        h = self.dt / self.substeps
        mass = self.hand_mass_kg
        q, qd = self.q, self.qd
        q_min, q_max = m.q_min, m.q_max
        for _ in range(self.substeps):
            m.update(q, qd)
            J = m.hip_jacobian()
            jdqd = m.hip_jdot_qd()
            inertia = m.mass_matrix()
            rhs = tau - m.nonlinear_effects() - self.friction * qd
            if mass > 0.0:
                inertia = inertia + mass * (J.T @ J)
                rhs = rhs - mass * (J.T @ jdqd)
            if forces is not None:
                f, tau_extra = forces(self.t, m.hip_position(), m.hip_velocity(), q, qd, J, inertia)
                rhs = rhs + J.T @ f + tau_extra
            else:
                f = np.zeros(3)
            qdd = np.linalg.solve(inertia, rhs)
            self._muscle = f
            self._hand_force = f - mass * (J @ qdd + jdqd)
            q, qd = _semi_implicit_step(q, qd, qdd, h, q_min, q_max)
            self.t += h
        self.q, self.qd = q, qd
        m.update(q, qd)
        return self.state()

    def _step_frozen(self, tau: FloatArray, forces: ForceModel | None) -> PlantState:
        """:meth:`step` with the configuration terms of the period's start (``frozen_dynamics``)."""
        m = self.model
        h = self.dt / self.substeps
        mass = self.hand_mass_kg
        q0, qd = self.q, self.qd
        if not (np.array_equal(m.q, q0) and np.array_equal(m.qd, qd)):
            m.update(q0, qd)  # else the previous period's end left it here
        J = m.hip_jacobian()
        jdqd = m.hip_jdot_qd()
        inertia = m.mass_matrix()
        bias = tau - m.nonlinear_effects()
        if mass > 0.0:
            inertia = inertia + mass * (J.T @ J)
            bias = bias - mass * (J.T @ jdqd)
        # One inverse for the period (M is symmetric positive definite and well conditioned):
        # each substep's solve becomes a product. NumPy's, not scipy's cho_factor: scipy's first
        # call loads its LAPACK wrappers (>10 ms), which at the enable starved the drives.
        inertia_inv = np.linalg.inv(inertia)
        inertia.setflags(write=False)  # the same array every substep: the patient may cache on it
        hip0 = m.hip_position()
        q = q0
        q_min, q_max = m.q_min, m.q_max
        f = np.zeros(3)
        qdd = np.zeros_like(qd)
        for _ in range(self.substeps):
            rhs = bias - self.friction * qd
            if forces is not None:
                hip = hip0 + J @ (q - q0)
                f, tau_extra = forces(self.t, hip, J @ qd, q, qd, J, inertia)
                rhs = rhs + J.T @ f + tau_extra
            qdd = inertia_inv @ rhs
            q, qd = _semi_implicit_step(q, qd, qdd, h, q_min, q_max)
            self.t += h
        self._muscle = f
        self._hand_force = f - mass * (J @ qdd + jdqd)
        self.q, self.qd = q, qd
        m.update(q, qd)
        return self.state()


def _semi_implicit_step(
    q: FloatArray, qd: FloatArray, qdd: FloatArray, h: float, q_min: FloatArray, q_max: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """One semi-implicit Euler substep of ``h`` (s) with the hard end stops: the joints clamped
    and their velocity into the stop dropped."""
    qd = qd + h * qdd
    q = q + h * qd
    low, high = q < q_min, q > q_max
    if low.any() or high.any():
        q = np.clip(q, q_min, q_max)
        qd = np.where((low & (qd < 0)) | (high & (qd > 0)), 0.0, qd)
    return q, qd


def solve_hip_ik(
    model: RobotModel,
    target: ArrayLike,
    q_start: ArrayLike | None = None,
    *,
    tolerance_m: float = 1e-4,
    iterations: int = 200,
    posture_weight: float = 0.2,
) -> tuple[FloatArray, float]:
    """Joint positions putting the HIP at ``target`` (m): damped least squares within the limits.

    Starts at ``q_start`` (default: the home configuration) and stays near it in the null space
    (``posture_weight``, a null-space pull per iteration, for the first half of the iterations),
    so the arm keeps a natural posture. Returns ``(q, error_m)``; the caller decides whether the
    remaining error means the target is out of reach.
    """
    goal = as_vector3(target, "target")
    q0 = np.array(model.q_home if q_start is None else q_start, dtype=np.float64)
    q = q0.copy()
    lo = model.q_min + 1e-3
    hi = model.q_max - 1e-3
    damping = 1e-4
    err = np.inf
    for k in range(iterations):
        # The posture pull stops for the last half, so it never holds the HIP off the target.
        pull = posture_weight if k < iterations // 2 else 0.0
        e = goal - model.hip_position_at(q)
        err = float(np.linalg.norm(e))
        if err < tolerance_m:
            break
        J = model.hip_jacobian_at(q)
        # Damped pseudo-inverse for the task, the posture pull in its null space.
        jj = J @ J.T + damping * np.eye(3)
        pinv = J.T @ np.linalg.inv(jj)
        dq = pinv @ e + pull * (q0 - q - pinv @ (J @ (q0 - q)))
        step = np.linalg.norm(dq)
        if step > 0.2:
            dq *= 0.2 / step
        q = np.clip(q + dq, lo, hi)
    return q, err


__all__ = ["ExoPlant", "ForceModel", "PlantState", "solve_hip_ik"]
