"""The controller's tasks: each builds its rows over the decision variables ``x = [qdd; tau]``.

One task per class, each with a small frozen configuration; ``rows(...)`` returns an
:class:`~.rows.Equality` or :class:`~.rows.Inequality` (named tuples) that the hierarchy stacks
into its levels. Tasks only check shapes: a NaN or inf in their inputs makes non-finite rows, which
the solver (and the controller before it) reports as invalid input instead of producing torques.

Prediction-style constraints (joint positions, fixed walls) keep a second-order prediction over a
horizon ``T`` inside the allowed set: ``d + T d' + T^2/2 d'' >= 0``. On the boundary this acts
like a spring-damper on ``d`` with stiffness ``2/T^2`` and damping ``2/T`` (damping ratio
``1/sqrt(2)``), so a longer horizon is softer and does not chatter; ``T`` never drops below the
control period. The paper writes the same constraint with a gain, ``T = k_p * dt`` (eqs. 9-11).
Rows of these constraints are scaled by ``2/T^2`` so their right-hand side is an acceleration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..config import StageConfig, param
from ..errors import InputError
from ..validation import as_finite_scalar, as_unit_vector3, as_vector3, read_only
from .rows import Equality, Inequality

FloatArray = NDArray[np.float64]


# ----- argument helpers ---------------------------------------------------------------------------
def shaped_array(value: ArrayLike, shape: tuple[int, ...], name: str) -> FloatArray:
    """``value`` as a float64 array of exactly ``shape`` (values are not checked: see module).

    The tasks' argument check; the controller makes it on their behalf for its stacked rows.
    """
    if type(value) is np.ndarray and value.dtype == np.float64 and value.shape == shape:
        return value  # the per-tick case: nothing to convert
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected real numbers") from None
    if arr.shape != shape:
        raise InputError(f"{name}: expected shape {shape}, got {arr.shape}")
    return arr


def control_period(dt: object) -> float:
    """``dt`` (s) as a positive finite float, or :class:`InputError` naming ``dt``."""
    if type(dt) is float and 0.0 < dt < math.inf:
        return dt  # the per-tick case
    value = as_finite_scalar(dt, "dt")
    if not value > 0.0:
        raise InputError(f"dt = {value}: must be positive")
    return value


def _n_joints(n_joints: object) -> int:
    if isinstance(n_joints, bool) or not isinstance(n_joints, int | np.integer) or n_joints < 1:
        raise InputError(f"n_joints = {n_joints!r}: expected a positive integer")
    return int(n_joints)


def _limit_vector(value: ArrayLike, n: int, name: str, *, allow_inf: bool) -> FloatArray:
    arr = shaped_array(np.reshape(value, -1), (n,), name)
    if np.isnan(arr).any() or (not allow_inf and not np.isfinite(arr).all()):
        raise InputError(f"{name}: must be {'numbers' if allow_inf else 'finite'}, got {arr}")
    return read_only(arr.copy())


def _selector(n: int, block: int, sign: float) -> FloatArray:
    """``sign * [I, 0]`` (block 0, the accelerations) or ``sign * [0, I]`` (block 1, torques)."""
    out = np.zeros((n, 2 * n))
    out[:, block * n : (block + 1) * n] = sign * np.eye(n)
    return out


# ----- 1: equation of motion ----------------------------------------------------------------------
@dataclass(frozen=True)
class EquationOfMotionConfig(StageConfig):
    """Parameters of :class:`EquationOfMotion`."""

    interaction_torque_scale: float = param(
        1.0,
        lo=0.0,
        hi=1.0,
        doc="fraction of the given interaction torque entered in the model (0 ignores it)",
    )


class EquationOfMotion:
    """Rigid-body dynamics ``M(q) qdd + h(q, qd) = tau + tau_int`` as ``[M, -I] x = tau_int - h``.

    ``tau_int`` is the joint torque of a measured interaction (``J^T f`` of a handle force
    sensor). Without one the patient's push is not in the model: the controller then only decides
    how the robot adds to it, which is what makes "minimise accelerations" transparent.

    Parameters
    ----------
    n_joints
        Number of joints ``n``; rows have ``2 n`` columns.
    config
        :class:`EquationOfMotionConfig`.
    """

    def __init__(self, n_joints: int, config: EquationOfMotionConfig | None = None) -> None:
        self.n = _n_joints(n_joints)
        self.config = config if config is not None else EquationOfMotionConfig()
        self._minus_eye = read_only(-np.eye(self.n))

    def rows(
        self,
        mass_matrix: ArrayLike,
        nonlinear_effects: ArrayLike,
        interaction_torque: ArrayLike | None = None,
    ) -> Equality:
        """Rows of the equation of motion.

        Parameters
        ----------
        mass_matrix
            ``M(q)``, shape ``(n, n)`` (symmetric positive definite).
        nonlinear_effects
            ``h(q, qd)``: Coriolis, centrifugal and gravity torques, shape ``(n,)``.
        interaction_torque
            ``tau_int``, shape ``(n,)``; scaled by ``interaction_torque_scale``.

        Returns
        -------
        Equality
            ``n`` rows named ``"equation_of_motion"``.
        """
        n = self.n
        M = shaped_array(mass_matrix, (n, n), "mass_matrix")
        h = shaped_array(nonlinear_effects, (n,), "nonlinear_effects")
        A = np.empty((n, 2 * n))
        A[:, :n] = M
        A[:, n:] = self._minus_eye
        tau_int = None
        if interaction_torque is not None:
            tau_int = shaped_array(interaction_torque, (n,), "interaction_torque")
        return Equality(A, self.rhs_into(h, tau_int, np.empty(n)), "equation_of_motion")

    @property
    def torque_block(self) -> FloatArray:
        """The constant ``-I`` of ``[M, -I]`` (read-only), the rows' ``tau`` columns."""
        return self._minus_eye

    def rhs_into(
        self, nonlinear_effects: FloatArray, interaction_torque: FloatArray | None, out: FloatArray
    ) -> FloatArray:
        """The right-hand side ``scale * tau_int - h`` written into ``out`` (shape ``(n,)``).

        The one formula of the rows' ``b``: :meth:`rows` and the controller's stacked rows both
        call it with checked float arrays.
        """
        b = np.negative(nonlinear_effects, out=out)
        if interaction_torque is not None:
            b += self.config.interaction_torque_scale * interaction_torque
        return b


# ----- 2: joint limits ----------------------------------------------------------------------------
@dataclass(frozen=True)
class JointPositionLimitConfig(StageConfig):
    """Parameters of :class:`JointPositionLimit`."""

    horizon_s: float = param(
        0.02,
        lo=0.0,
        hi=1.0,
        unit="s",
        doc="prediction horizon T of q + T qd + T^2/2 qdd (longer is softer; at least dt)",
    )
    margin_rad: float = param(
        0.0, lo=0.0, hi=0.5, unit="rad", doc="keep this far inside [q_min, q_max]"
    )


class JointPositionLimit:
    """``q_min + m <= q + T qd + T^2/2 qdd <= q_max - m``: ``2 n`` inequality rows.

    Rows are ``+-[I, 0] x <= +-2 (bound - q - T qd) / T^2``. Infinite bounds give rows that
    are never active. When the joint cannot stop in time (or starts outside), the rows ask for
    more than the torques allow; the hierarchy then relaxes them by the least amount.

    Parameters
    ----------
    q_min, q_max
        Joint position limits, shape ``(n,)``, ``q_min < q_max`` (``+-inf`` allowed).
    config
        :class:`JointPositionLimitConfig`.
    """

    def __init__(
        self, q_min: ArrayLike, q_max: ArrayLike, config: JointPositionLimitConfig | None = None
    ) -> None:
        self.config = config if config is not None else JointPositionLimitConfig()
        self.n = _n_joints(np.size(q_min))
        self.q_min = _limit_vector(q_min, self.n, "q_min", allow_inf=True)
        self.q_max = _limit_vector(q_max, self.n, "q_max", allow_inf=True)
        margin = self.config.margin_rad
        if not np.all(self.q_max - self.q_min > 2.0 * margin):
            raise InputError(
                f"q_min, q_max: every joint needs q_max - q_min > 2 * margin_rad ({2 * margin}), "
                f"got q_min={self.q_min.tolist()} q_max={self.q_max.tolist()}"
            )
        self._upper = read_only(self.q_max - margin)
        self._lower = read_only(self.q_min + margin)
        self._G = read_only(np.vstack([_selector(self.n, 0, 1.0), _selector(self.n, 0, -1.0)]))

    @property
    def matrix(self) -> FloatArray:
        """The constant matrix ``[[I, 0], [-I, 0]]`` of the rows (read-only)."""
        return self._G

    def horizon_s(self, dt: float) -> float:
        """The horizon actually used: ``max(horizon_s, dt)``."""
        return max(self.config.horizon_s, control_period(dt))

    def rows(self, q: ArrayLike, qd: ArrayLike, dt: float) -> Inequality:
        """Rows for joint positions ``q`` and velocities ``qd`` (shape ``(n,)``), period ``dt``."""
        n = self.n
        q = shaped_array(q, (n,), "q")
        qd = shaped_array(qd, (n,), "qd")
        return Inequality(
            self._G, self.bounds_into(q, qd, dt, np.empty(2 * n)), "joint_position_limit"
        )

    def bounds_into(self, q: FloatArray, qd: FloatArray, dt: float, out: FloatArray) -> FloatArray:
        """The rows' right-hand side ``+-2 (bound - q - T qd) / T^2`` written into ``out``.

        The one formula of the rows: :meth:`rows` and the controller's stacked rows call it with
        checked float arrays (``out`` of shape ``(2 n,)``, upper bounds first).
        """
        n = self.n
        T = self.horizon_s(dt)
        predicted = q + T * qd
        # inf - finite stays inf: unlimited joints give inactive rows, never NaN.
        np.subtract(self._upper, predicted, out=out[:n])
        np.subtract(predicted, self._lower, out=out[n:])
        out *= 2.0 / (T * T)
        return out

    def check_bounds(self, dt: float, tol: float) -> tuple[float, float, list[float], list[float]]:
        """``(T, T^2/2, upper + tol, lower - tol)``: the rows as a test of one ``x``.

        ``q + T qd + T^2/2 qdd`` within ``[lower - tol, upper + tol]`` is the same inequality as
        the rows, in the prediction form a per-joint check evaluates cheaply
        (:meth:`JointLimitCheck.admits`).
        """
        T = self.horizon_s(dt)
        return T, 0.5 * T * T, (self._upper + tol).tolist(), (self._lower - tol).tolist()


@dataclass(frozen=True)
class JointVelocityLimitConfig(StageConfig):
    """Parameters of :class:`JointVelocityLimit`."""

    horizon_s: float = param(
        0.01,
        lo=0.0,
        hi=1.0,
        unit="s",
        doc="time T in which qd + T qdd must be within the limit (longer is softer; at least dt)",
    )


class JointVelocityLimit:
    """``-v_max <= qd + T qdd <= v_max``: ``2 n`` inequality rows ``+-[I, 0] x <= ...``.

    Parameters
    ----------
    v_max
        Joint speed limits, shape ``(n,)``, positive (``inf`` allowed).
    config
        :class:`JointVelocityLimitConfig`.
    """

    def __init__(self, v_max: ArrayLike, config: JointVelocityLimitConfig | None = None) -> None:
        self.config = config if config is not None else JointVelocityLimitConfig()
        self.n = _n_joints(np.size(v_max))
        self.v_max = _limit_vector(v_max, self.n, "v_max", allow_inf=True)
        if not np.all(self.v_max > 0):
            raise InputError(f"v_max: must be positive, got {self.v_max.tolist()}")
        self._G = read_only(np.vstack([_selector(self.n, 0, 1.0), _selector(self.n, 0, -1.0)]))

    @property
    def matrix(self) -> FloatArray:
        """The constant matrix ``[[I, 0], [-I, 0]]`` of the rows (read-only)."""
        return self._G

    def horizon_s(self, dt: float) -> float:
        """The horizon actually used: ``max(horizon_s, dt)``."""
        return max(self.config.horizon_s, control_period(dt))

    def rows(self, qd: ArrayLike, dt: float) -> Inequality:
        """Rows for joint velocities ``qd`` (shape ``(n,)``), period ``dt``."""
        qd = shaped_array(qd, (self.n,), "qd")
        return Inequality(
            self._G, self.bounds_into(qd, dt, np.empty(2 * self.n)), "joint_velocity_limit"
        )

    def bounds_into(self, qd: FloatArray, dt: float, out: FloatArray) -> FloatArray:
        """The rows' right-hand side ``(v_max -+ qd) / T`` written into ``out`` (``(2 n,)``).

        The one formula of the rows: :meth:`rows` and the controller's stacked rows call it.
        """
        n = self.n
        np.subtract(self.v_max, qd, out=out[:n])
        np.add(self.v_max, qd, out=out[n:])
        out /= self.horizon_s(dt)
        return out

    def check_bounds(self, dt: float, tol: float) -> tuple[float, list[float]]:
        """``(T, v_max + tol)``: the rows as a test of one ``x`` (``|qd + T qdd| <= v_max``)."""
        return self.horizon_s(dt), (self.v_max + tol).tolist()


@dataclass(frozen=True)
class TorqueLimitConfig(StageConfig):
    """Parameters of :class:`TorqueLimit`."""

    scale: float = param(
        1.0,
        lo=0.0,
        hi=1.0,
        lo_open=True,
        doc="fraction of the drive limit the solver may use (the output is clamped to 1.0)",
    )


class TorqueLimit:
    """``|tau| <= scale * tau_max``: ``2 n`` constant inequality rows ``+-[0, I] x <= ...``.

    Parameters
    ----------
    tau_max
        Drive torque limits, shape ``(n,)``, positive and finite.
    config
        :class:`TorqueLimitConfig`.
    """

    def __init__(self, tau_max: ArrayLike, config: TorqueLimitConfig | None = None) -> None:
        self.config = config if config is not None else TorqueLimitConfig()
        self.n = _n_joints(np.size(tau_max))
        self.tau_max = _limit_vector(tau_max, self.n, "tau_max", allow_inf=False)
        if not np.all(self.tau_max > 0):
            raise InputError(f"tau_max: must be positive, got {self.tau_max.tolist()}")
        G = np.vstack([_selector(self.n, 1, 1.0), _selector(self.n, 1, -1.0)])
        h = self.config.scale * np.concatenate([self.tau_max, self.tau_max])
        # Constant rows: built once, handed out read-only every tick.
        self._rows = Inequality(read_only(G), read_only(h), "torque_limit")

    def rows(self) -> Inequality:
        """The (constant) rows."""
        return self._rows

    def check_bounds(self, tol: float) -> list[float]:
        """``scale tau_max (1 + tol)``: the rows as a test of one ``x``, relative tolerance."""
        return (self.config.scale * self.tau_max * (1.0 + tol)).tolist()


class JointLimitCheck(NamedTuple):
    """Levels 1-2's inequalities (torque, joint position and velocity limits) as a test of one
    ``x``, joint by joint on Python floats (cheaper than building their rows).

    Built by :meth:`~.controller.HierarchicalController.limit_check` from the tasks'
    ``check_bounds``; :meth:`admits` is the one place that evaluates them this way.
    """

    tau: list[float]
    horizon: float
    half_horizon_sq: float
    q_hi: list[float]
    q_lo: list[float]
    v_horizon: float
    v: list[float]

    def admits(self, tau: list[float], q: list[float], qd: list[float], qdd: list[float]) -> bool:
        """``|tau| <= tau_max``, ``q + T qd + T^2/2 qdd`` within the limits and
        ``|qd + T_v qdd| <= v_max``, every joint (bounds widened by the tolerance)."""
        T, half_T2, Tv = self.horizon, self.half_horizon_sq, self.v_horizon
        for tau_i, q_i, qd_i, qdd_i, tau_max, q_hi, q_lo, v_max in zip(
            tau, q, qd, qdd, self.tau, self.q_hi, self.q_lo, self.v, strict=True
        ):
            if abs(tau_i) > tau_max:
                return False
            q_pred = q_i + T * qd_i + half_T2 * qdd_i
            if q_pred > q_hi or q_pred < q_lo or abs(qd_i + Tv * qdd_i) > v_max:
                return False
        return True


# ----- 3: fixed walls -----------------------------------------------------------------------------
@dataclass(frozen=True)
class FixedWallsConfig(StageConfig):
    """Parameters of :class:`FixedWalls`."""

    horizon_s: float = param(
        0.01,
        lo=0.0,
        hi=1.0,
        unit="s",
        doc="prediction horizon T = k_p dt of d + T d' + T^2/2 d'' >= 0 (longer is softer)",
    )
    margin_m: float = param(
        0.04, lo=0.0, hi=0.5, unit="m", doc="distance kept between the HIP and each plane"
    )
    activation_distance_m: float = param(
        0.5, lo=0.0, hi=100.0, unit="m", doc="planes farther than this from the HIP give no row"
    )


class FixedWalls:
    """Static virtual planes the HIP must stay in front of (priority 3).

    Wall ``i`` is a point ``o_i`` and a unit normal ``n_i`` pointing to the allowed side; its
    free distance is ``d_i = n_i . (p - o_i) - margin`` for the HIP at ``p``, with
    ``d_i' = n_i^T J qd`` and ``d_i'' = n_i^T (J qdd + Jdot qd)``. Each wall within the activation
    distance gives the row ``-(n_i^T J) qdd <= 2/T^2 (d_i + T d_i') + n_i^T Jdot qd``.

    Parameters
    ----------
    points, normals
        Shape ``(k, 3)`` each, world frame; normals are normalised (zero ones are an error).
    n_joints
        Number of joints ``n``.
    config
        :class:`FixedWallsConfig`.
    """

    def __init__(
        self,
        points: ArrayLike,
        normals: ArrayLike,
        n_joints: int,
        config: FixedWallsConfig | None = None,
    ) -> None:
        self.config = config if config is not None else FixedWallsConfig()
        self.n = _n_joints(n_joints)
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        if pts.shape != nrm.shape:
            raise InputError(f"points, normals: shapes differ, {pts.shape} and {nrm.shape}")
        self.points = read_only(
            np.array([as_vector3(p, f"points[{i}]") for i, p in enumerate(pts)]).reshape(-1, 3)
        )
        self.normals = read_only(
            np.array([as_unit_vector3(v, f"normals[{i}]") for i, v in enumerate(nrm)]).reshape(
                -1, 3
            )
        )
        # n_i . o_i, so that d = N p - offsets - margin needs one product per tick.
        self._offsets = np.einsum("ij,ij->i", self.normals, self.points)

    @property
    def n_walls(self) -> int:
        """Number of planes."""
        return self.points.shape[0]

    def distances(self, hip_position: ArrayLike) -> FloatArray:
        """Free distance ``d_i`` of the HIP to each plane (margin subtracted), shape ``(k,)``."""
        p = shaped_array(hip_position, (3,), "hip_position")
        return self.normals @ p - self._offsets - self.config.margin_m

    def rows(
        self,
        hip_position: ArrayLike,
        hip_jacobian: ArrayLike,
        hip_jdot_qd: ArrayLike,
        qd: ArrayLike,
        dt: float,
    ) -> Inequality:
        """Rows of the walls within the activation distance.

        Parameters
        ----------
        hip_position
            HIP position ``p`` in the world frame, shape ``(3,)``.
        hip_jacobian
            Translational Jacobian of the HIP, world frame, shape ``(3, n)``.
        hip_jdot_qd
            ``Jdot qd`` of the HIP, shape ``(3,)``.
        qd
            Joint velocities, shape ``(n,)``.
        dt
            Control period (s).

        Returns
        -------
        Inequality
            One row per active wall (possibly none), named ``"fixed_walls"``.
        """
        n = self.n
        J = shaped_array(hip_jacobian, (3, n), "hip_jacobian")
        jdqd = shaped_array(hip_jdot_qd, (3,), "hip_jdot_qd")
        qd = shaped_array(qd, (n,), "qd")
        T = max(self.config.horizon_s, control_period(dt))
        normals = self.normals
        d = self.distances(hip_position)
        if d.min() >= self.config.activation_distance_m:
            return Inequality(np.zeros((0, 2 * n)), np.zeros(0), "fixed_walls")
        if d.max() >= self.config.activation_distance_m:
            active = d < self.config.activation_distance_m
            normals = normals[active]
            d = d[active]
        Jc = normals @ J
        G = np.zeros((Jc.shape[0], 2 * n))
        np.negative(Jc, out=G[:, :n])
        # 2/T^2 (d + T Jc qd) + N Jdot qd, with one product by the normals.
        gain = 2.0 / (T * T)
        h = normals @ jdqd + gain * (d + T * (Jc @ qd))
        return Inequality(G, h, "fixed_walls")


# ----- 5: minimise accelerations / motion --------------------------------------------------------
@dataclass(frozen=True)
class MinimizeAccelerationConfig(StageConfig):
    """Parameters of :class:`MinimizeAcceleration`."""

    damping_1_per_s: float = param(
        0.0,
        lo=0.0,
        hi=100.0,
        unit="1/s",
        doc="target qdd = -damping * qd (0: the paper's plain minimum of the accelerations)",
    )


class MinimizeAcceleration:
    """``qdd = -D qd`` (``D = 0`` by default): ``n`` equality rows ``[I, 0] x = -D qd``.

    With the equation of motion above it, ``qdd = 0`` means ``tau = h``: the model's gravity and
    Coriolis torques, so the robot is transparent to a push that is not in its model. Torque
    regularisation is the solver's Tikhonov metric, which only acts on freedom left by all tasks.

    Parameters
    ----------
    n_joints
        Number of joints ``n``.
    config
        :class:`MinimizeAccelerationConfig`.
    """

    def __init__(self, n_joints: int, config: MinimizeAccelerationConfig | None = None) -> None:
        self.config = config if config is not None else MinimizeAccelerationConfig()
        self.n = _n_joints(n_joints)
        self._A = read_only(_selector(self.n, 0, 1.0))
        self._zero = read_only(np.zeros(self.n))

    def rows(self, qd: ArrayLike | None = None) -> Equality:
        """Rows; ``qd`` (shape ``(n,)``) is needed only when damping is set."""
        damping = self.config.damping_1_per_s
        if damping == 0.0:
            return Equality(self._A, self._zero, "minimize_acceleration")
        if qd is None:
            raise InputError("qd: required when damping_1_per_s > 0")
        return Equality(
            self._A, -damping * shaped_array(qd, (self.n,), "qd"), "minimize_acceleration"
        )


def _saturate(acc: FloatArray, limit: float) -> FloatArray:
    """Scale ``acc`` down to norm ``limit`` keeping its direction (guarded division)."""
    norm = float(np.sqrt(acc @ acc))
    if norm > limit and norm > 0.0:
        return acc * (limit / norm)
    return acc


@dataclass(frozen=True)
class JointMotionConfig(StageConfig):
    """Parameters of :class:`JointMotionTask`."""

    stiffness_1_per_s2: float = param(
        100.0, lo=0.0, hi=1e5, unit="1/s^2", log_scale=True, doc="PD stiffness K_p"
    )
    damping_1_per_s: float = param(20.0, lo=0.0, hi=1e3, unit="1/s", doc="PD damping K_d")
    max_acceleration_rad_per_s2: float = param(
        100.0,
        lo=0.0,
        hi=1e4,
        lo_open=True,
        unit="rad/s^2",
        doc="norm limit of the commanded joint acceleration",
    )


class JointMotionTask:
    """Track a joint target: ``qdd = qdd_t + K_p (q_t - q) + K_d (qd_t - qd)``, ``n`` equalities.

    Parameters
    ----------
    n_joints
        Number of joints ``n``.
    config
        :class:`JointMotionConfig`.
    """

    def __init__(self, n_joints: int, config: JointMotionConfig | None = None) -> None:
        self.config = config if config is not None else JointMotionConfig()
        self.n = _n_joints(n_joints)
        self._A = read_only(_selector(self.n, 0, 1.0))

    def rows(
        self,
        q: ArrayLike,
        qd: ArrayLike,
        q_target: ArrayLike,
        qd_target: ArrayLike | None = None,
        qdd_target: ArrayLike | None = None,
    ) -> Equality:
        """Rows towards ``q_target`` (and ``qd_target``, feed-forward ``qdd_target``)."""
        n, cfg = self.n, self.config
        q = shaped_array(q, (n,), "q")
        qd = shaped_array(qd, (n,), "qd")
        acc = cfg.stiffness_1_per_s2 * (shaped_array(q_target, (n,), "q_target") - q)
        v_target = np.zeros(n) if qd_target is None else shaped_array(qd_target, (n,), "qd_target")
        acc += cfg.damping_1_per_s * (v_target - qd)
        if qdd_target is not None:
            acc += shaped_array(qdd_target, (n,), "qdd_target")
        return Equality(self._A, _saturate(acc, cfg.max_acceleration_rad_per_s2), "joint_motion")


@dataclass(frozen=True)
class HipMotionConfig(StageConfig):
    """Parameters of :class:`HipMotionTask`."""

    stiffness_1_per_s2: float = param(
        100.0, lo=0.0, hi=1e5, unit="1/s^2", log_scale=True, doc="PD stiffness K_p"
    )
    damping_1_per_s: float = param(20.0, lo=0.0, hi=1e3, unit="1/s", doc="PD damping K_d")
    max_acceleration_m_per_s2: float = param(
        20.0,
        lo=0.0,
        hi=1e3,
        lo_open=True,
        unit="m/s^2",
        doc="norm limit of the commanded HIP acceleration",
    )


class HipMotionTask:
    """Track a HIP target: ``J qdd + Jdot qd = a_t + K_p (p_t - p) + K_d (v_t - J qd)``.

    Three equality rows ``[J, 0] x = a - Jdot qd``; the joints' remaining freedom is left to the
    levels below (the controller puts :class:`MinimizeAcceleration` there).

    Parameters
    ----------
    n_joints
        Number of joints ``n``.
    config
        :class:`HipMotionConfig`.
    """

    def __init__(self, n_joints: int, config: HipMotionConfig | None = None) -> None:
        self.config = config if config is not None else HipMotionConfig()
        self.n = _n_joints(n_joints)

    def rows(
        self,
        hip_position: ArrayLike,
        hip_jacobian: ArrayLike,
        hip_jdot_qd: ArrayLike,
        qd: ArrayLike,
        target_position: ArrayLike,
        target_velocity: ArrayLike | None = None,
        target_acceleration: ArrayLike | None = None,
    ) -> Equality:
        """Rows towards ``target_position`` (world frame, shape ``(3,)``)."""
        n, cfg = self.n, self.config
        p = shaped_array(hip_position, (3,), "hip_position")
        J = shaped_array(hip_jacobian, (3, n), "hip_jacobian")
        jdqd = shaped_array(hip_jdot_qd, (3,), "hip_jdot_qd")
        qd = shaped_array(qd, (n,), "qd")
        v = J @ qd
        acc = cfg.stiffness_1_per_s2 * (shaped_array(target_position, (3,), "target_position") - p)
        v_target = (
            np.zeros(3)
            if target_velocity is None
            else shaped_array(target_velocity, (3,), "target_velocity")
        )
        acc += cfg.damping_1_per_s * (v_target - v)
        if target_acceleration is not None:
            acc += shaped_array(target_acceleration, (3,), "target_acceleration")
        acc = _saturate(acc, cfg.max_acceleration_m_per_s2)
        A = np.zeros((3, 2 * n))
        A[:, :n] = J
        return Equality(A, acc - jdqd, "hip_motion")


__all__ = [
    "EquationOfMotion",
    "EquationOfMotionConfig",
    "FixedWalls",
    "FixedWallsConfig",
    "HipMotionConfig",
    "HipMotionTask",
    "JointLimitCheck",
    "JointMotionConfig",
    "JointMotionTask",
    "JointPositionLimit",
    "JointPositionLimitConfig",
    "JointVelocityLimit",
    "JointVelocityLimitConfig",
    "MinimizeAcceleration",
    "MinimizeAccelerationConfig",
    "TorqueLimit",
    "TorqueLimitConfig",
]
