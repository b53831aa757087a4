"""The haptic control tick (800 Hz): fused surface and walls in, clamped joint torques out.

One :meth:`HapticLoop.tick` does, in this order:

1. ``robot.update(q, qd)``: HIP position, translational Jacobian, ``Jdot qd``, ``M``, ``h``;
2. ``fusion.sample(t)`` (when the scene has cameras): the smooth surface at ``t``, extrapolated
   with the regression's velocity between camera frames;
3. one :class:`~hapticloud.core.haptics.HapticState` per surface (the fused one and every
   ``haptic`` wall) and its constraint rows (positional, velocity, force) for level 4;
4. :meth:`HierarchicalController.step` with those rows, the fixed walls at level 3, the measured
   interaction torque (if the robot has a handle force sensor) and the transparency task at
   level 5 (``tau = h``: the robot compensates only its own dynamics);
5. telemetry: free distance and approach speed of the nearest surface, which constraints had
   rows, the level-4 violation and the timings (which rows bound the solution is evaluated on
   demand, :meth:`HapticLoop.last_binding`, outside the timed tick).

Everything here is pure (no threads, no I/O, no clock but ``perf_counter`` for telemetry); the
hardware layer's control process calls the same :meth:`HapticLoop.tick` from its
``ControlTick`` (``hardware/control/tick.py``). The refit of the fusion's regression is left to
the caller (``fusion.prepare()`` right after ``fusion.add``: the simulator between ticks, the
control process after the tick's command is out), so a tick only evaluates the cached polynomial.

Why ``tau = h`` at level 5 rather than "minimise joint accelerations": without a force sensor
they are the same task (``M qdd + h = tau`` and ``qdd = 0``). With the handle's force sensor the
measured interaction torque is in the equation of motion, and ``qdd = 0`` would then mean holding
the arm still against the patient; ``tau = h`` keeps the robot transparent while the constraints
above it act on the accelerations the patient's force really causes.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import lapack

from .config import StageConfig, nested, param
from .control import (
    LEVEL_NAMES,
    ControlOutput,
    ControlStatus,
    Equality,
    HierarchicalController,
    Inequality,
)
from .control.controller import StepInputs
from .control.reductions import finite_total, or_reduce
from .control.tasks import JointLimitCheck
from .errors import InputError
from .fusion import FusedSurface, SurfaceFusion
from .haptics import (
    ForceConstraint,
    ForceConstraintConfig,
    HapticState,
    HipState,
    PositionalConstraint,
    PositionalConstraintConfig,
    SurfacePoint,
    VelocityConstraint,
    VelocityConstraintConfig,
    haptic_state,
)
from .haptics.distance import check_dt, trusted_haptic_state
from .haptics.force import mass_factor
from .haptics.unknown import (
    SpaceState,
    SurfaceGuard,
    UnknownSpaceConfig,
    free_proof_holds,
    hold_acceleration,
)
from .perception import SurfaceEstimate
from .validation import as_finite_scalar, as_unit_vector3, as_vector3

FloatArray = NDArray[np.float64]

#: Bits of :attr:`TickResult.rows` and of :meth:`HapticLoop.last_binding`.
POSITIONAL, VELOCITY, FORCE = 1, 2, 4

#: Half-width of the band (m/s²) the tangential rows hold the HIP's acceleration in.
TANGENT_BAND_M_S2 = 0.02

# Rows within this (relative) of their bound count as met by the shortcut: the equality pairs of
# the tangential rows sit exactly on it, up to rounding.
_SHORTCUT_TOL = 1e-9

# Internal bits of the shared motion row: both constraints present, and which one is tighter.
_TIGHTER, _POS_TIGHTER = 8, 16

#: A row counts as binding when ``G x`` is within this of ``h`` (m/s², solver tolerance scale).
BINDING_TOL = 1e-6

_ZERO3 = np.zeros(3)
_ZERO3.setflags(write=False)
_UNIT_Z = np.array([0.0, 0.0, 1.0])
_UNIT_Z.setflags(write=False)


@dataclass(frozen=True)
class HapticsConfig(StageConfig):
    """Which haptic constraints the tick builds, and their parameters (scene table ``haptics``)."""

    _path: ClassVar[str] = "haptics"

    positional_enabled: bool = param(True, doc="build the positional constraint (eqs. 9-11)")
    velocity_enabled: bool = param(True, doc="build the velocity constraint (eqs. 12-14)")
    force_enabled: bool = param(True, doc="build the ISO/TS 15066 force constraint")
    transparent: bool = param(
        True,
        doc="level 5 is tau = h (transparent); false: the paper's minimum joint accelerations",
    )
    clearance_m: float = param(
        0.002,
        lo=0.0,
        hi=0.05,
        unit="m",
        doc="extra distance the constraints keep beyond the HIP radius (estimate error allowance)",
    )
    exact_shortcut: bool = param(
        True,
        doc="skip the solver when the level-5 torques already meet every constraint (exact)",
    )
    frictionless: bool = param(
        True,
        doc="near a surface, hold the HIP's tangential acceleration at the transparent one",
    )
    positional: PositionalConstraintConfig = nested(PositionalConstraintConfig)
    velocity: VelocityConstraintConfig = nested(VelocityConstraintConfig)
    force: ForceConstraintConfig = nested(ForceConstraintConfig)
    unknown: UnknownSpaceConfig = nested(UnknownSpaceConfig)

    def paper(self) -> HapticsConfig:
        """The same parameters with the paper's formulation: no surface-velocity feed-forward."""
        return self.with_overrides(
            {
                "positional.surface_velocity_feedforward": False,
                "velocity.surface_velocity_feedforward": False,
            }
        )


class Wall(NamedTuple):
    """A static virtual plane (world frame).

    ``normal`` is unit and points to the allowed side. ``level`` is ``"haptic"`` (rendered by the
    haptic constraints at level 4, like a perceived surface: the paper's Fig. 11 plane) or
    ``"fixed"`` (the controller's fixed collision constraint at level 3). ``part`` is the body
    region whose ISO/TS 15066 force limit applies ("" = the force constraint's default).
    """

    name: str
    point: FloatArray
    normal: FloatArray
    level: str = "haptic"
    part: str = ""

    @classmethod
    def make(
        cls, name: str, point: ArrayLike, normal: ArrayLike, level: str = "haptic", part: str = ""
    ) -> Wall:
        """Validated construction (finite point, non-zero normal, known level)."""
        if level not in ("haptic", "fixed"):
            raise InputError(f"walls[{name}].level = {level!r}: must be haptic or fixed")
        p = as_vector3(point, f"walls[{name}].point").copy()
        n = as_unit_vector3(normal, f"walls[{name}].normal").copy()
        p.setflags(write=False)
        n.setflags(write=False)
        return cls(name, p, n, level, part)

    def distance(self, x: ArrayLike) -> float:
        """Signed distance (m) of point ``x`` from the plane, positive on the allowed side."""
        return float(self.normal @ (np.asarray(x, dtype=np.float64) - self.point))

    def closest(self, x: FloatArray) -> FloatArray:
        """The plane's point closest to ``x``."""
        return x - (self.normal @ (x - self.point)) * self.normal


class TickResult(NamedTuple):
    """What one :meth:`HapticLoop.tick` returns.

    Attributes
    ----------
    tau
        Joint torques to send (N m), clamped to the drive limits, never NaN.
    qdd
        Joint accelerations the model predicts for ``tau`` (rad/s²).
    status
        The controller's :class:`~hapticloud.core.control.ControlStatus`.
    d_proj_m
        Free distance of the HIP sphere (radius ``hip_radius_m``, without the clearance) to the
        nearest surface the tick knows (m; ``inf`` with none).
    approach_mps
        Approach speed towards that surface (m/s, positive = closing), relative to the surface
        when its constraint uses the surface-velocity feed-forward.
    nearest
        Which surface: -1 none, 0 the fused (or held) surface, ``1 + i`` haptic wall ``i``.
    rows
        Bits :data:`POSITIONAL` | :data:`VELOCITY` | :data:`FORCE`: constraint types with rows
        (which of them bound the solution: :meth:`HapticLoop.last_binding`).
    violation
        Norm of the level-4 (haptic) violation after the solve (m/s²; 0 when all held).
    fused_valid
        The fusion gave a valid surface this tick (False without cameras).
    solve_us, step_us, tick_us
        Hierarchy solve, controller step, and the whole tick (µs).
    clamped
        The torque clamp changed the solver's torques.
    space
        What the tick knew of the space around the HIP (:class:`SpaceState`: known, holding the
        last surface, stopped); always ``KNOWN`` in a scene without cameras.
    """

    tau: FloatArray
    qdd: FloatArray
    status: ControlStatus
    d_proj_m: float
    approach_mps: float
    nearest: int
    rows: int
    violation: float
    fused_valid: bool
    solve_us: float
    step_us: float
    tick_us: float
    clamped: bool
    space: SpaceState = SpaceState.KNOWN


class HapticLoop:
    """The control tick: fusion sample, haptic constraints, hierarchy, clamped torques.

    Parameters
    ----------
    robot
        A :class:`~hapticloud.core.robot.RobotModel` (this loop owns its per-tick state).
    controller
        The hierarchical controller, built with the fixed walls (level 3) if any.
    haptics
        Which constraints and their gains.
    hip_radius_m
        HIP radius (m), the safety offset of ``d_proj``.
    dt
        Control period (s).
    fusion
        The surface fusion fed by the cameras; ``None`` when the scene has none.
    walls
        Walls; those with ``level == "haptic"`` are rendered by the haptic constraints here
        (``"fixed"`` ones belong to the controller and are ignored here).
    fused_region
        ISO/TS 15066 region assumed for the perceived surface ("" = the force constraint's
        default, the strictest: face).

    Notes
    -----
    The rows are the haptics module's (:class:`~hapticloud.core.haptics.PositionalConstraint`,
    :class:`~hapticloud.core.haptics.VelocityConstraint`,
    :class:`~hapticloud.core.haptics.ForceConstraint`), evaluated here into one preallocated
    buffer: their per-call argument checks and small allocations cost ~20 µs of a budget of
    150 µs (``tests/core/test_loop.py`` checks that both give the same rows). The positional and the
    velocity rows of one surface share ``G = [-J_c, 0]``, so they are one row with the smaller
    right-hand side: only the tighter of two parallel half-spaces can bind.
    """

    def __init__(
        self,
        robot: Any,
        controller: HierarchicalController,
        haptics: HapticsConfig | None = None,
        *,
        hip_radius_m: float,
        dt: float,
        fusion: SurfaceFusion | None = None,
        walls: Sequence[Wall] = (),
        fused_region: str = "",
    ) -> None:
        self.robot = robot
        self.controller = controller
        self.config = haptics if haptics is not None else HapticsConfig()
        self.hip_radius_m = as_finite_scalar(hip_radius_m, "hip_radius_m")
        if self.hip_radius_m < 0.0:
            raise InputError(f"hip_radius_m = {self.hip_radius_m}: must be >= 0")
        self.dt = check_dt(dt)
        self.fusion = fusion
        self.walls = tuple(w for w in walls if w.level == "haptic")
        self.fused_region = fused_region
        #: Unknown is not free: what the tick does without a valid fused surface.
        self.guard = SurfaceGuard(self.config.unknown)
        self.configure(self.config)
        n = controller.n_joints
        self.n_joints = n
        # Level 5, tau = h: [0, I] x = h. The matrix is constant; only b changes per tick.
        a_tau = np.zeros((n, 2 * n))
        a_tau[:, n:] = np.eye(n)
        a_tau.setflags(write=False)
        self._a_tau = a_tau
        # Row buffer: per surface a motion row and a force row, plus 2 tangents x 2 rows.
        capacity = 2 * (1 + len(self.walls)) + 4
        self._G = np.zeros((capacity, 2 * n))
        self._h = np.zeros(capacity)
        self._kind = [0] * capacity
        self._rows_written = 0
        # As float arrays (a Wall built directly may hold lists): the tick's products need them.
        self._wall_surfaces = [
            SurfacePoint(_float_array(w.point), _float_array(w.normal), _ZERO3, w.part)
            for w in self.walls
        ]
        self._solved_last = False
        # Level 5 of the position hold while stopped: [I, 0] x = qdd_hold.
        a_hold = np.zeros((n, 2 * n))
        a_hold[:, :n] = np.eye(n)
        a_hold.setflags(write=False)
        self._a_hold = a_hold
        self._cap: float | None = None
        self._n_haptic = 0
        self._last_x: tuple[FloatArray, FloatArray] | None = None
        self.last_fused: FusedSurface | None = None
        #: Cap on the approach speed towards every surface in reach (m/s), on top of the velocity
        #: constraint's own bound; ``None``: none. A session's watchdog sets it to v_min while it
        #: holds a surface it can no longer see (a stale camera or estimate).
        self.approach_limit_mps: float | None = None
        self._limits: JointLimitCheck | None = None
        self._limits_for: HierarchicalController | None = None
        from .robot import RobotModel  # pinocchio: loaded by the model's owner already

        # Only the shipped model's state is known to be float arrays of the right shapes.
        self._trusted = isinstance(robot, RobotModel)

    def configure(self, haptics: HapticsConfig) -> None:
        """Use ``haptics`` from the next tick on (a few µs: tuning while the loop runs)."""
        cfg = haptics
        positional = PositionalConstraint(cfg.positional)
        velocity = VelocityConstraint(cfg.velocity)
        force = ForceConstraint(cfg.force)
        # Force limits per region (validated now: an unknown region is a scene error).
        force_limit = {
            region: force.force_limit_n(SurfacePoint(_ZERO3, _UNIT_Z, _ZERO3, region))
            for region in {self.fused_region, *(w.part for w in self.walls)}
        }
        self.config = cfg
        self.guard.configure(cfg.unknown)
        self.positional, self.velocity, self.force = positional, velocity, force
        self._force_limit = force_limit
        self._act_motion = max(
            cfg.positional.activation_distance_m if cfg.positional_enabled else -math.inf,
            cfg.velocity.activation_distance_m if cfg.velocity_enabled else -math.inf,
        )

    def warm_up(self, t: float, q: ArrayLike, qd: ArrayLike) -> None:
        """Run the tick's every path once (free motion, a surface in reach, in contact) and
        forget them: the first solve of a hierarchy allocates its work space and fills lazy
        caches (~10 ms measured); a real-time loop calls this before its first deadline."""
        self.robot.update(q, qd)
        hip = np.array(self.robot.hip_position())
        normal = np.array([0.0, 0.0, 1.0])
        saved = self.fusion
        self.fusion = None
        try:
            for gap in (1.0, 0.02, 0.002, -0.002):
                point = hip - normal * (self.hip_radius_m + gap)
                fused = FusedSurface(
                    t, point, normal, True, _ZERO3, point, normal, 0.0, False, "", 3, 2, (), 0
                )
                self.tick(t, q, qd, fused=fused)
            self.tick(t, q, qd, interaction_torque=np.zeros(self.n_joints))
            lost = FusedSurface(
                t, hip, normal, False, _ZERO3, hip, normal, 1.0, True, "warm-up", 0, 0, (), 0
            )
            self.tick(t, q, qd, fused=lost)  # holding
            self.tick(t + 10.0, q, qd, fused=lost)  # stopped: the position hold
        finally:
            self.fusion = saved
            self.guard = SurfaceGuard(self.config.unknown)  # and no warm-up in its log
            self._solved_last = False
            self._last_x = None
            self.last_fused = None

    # ----- one tick ------------------------------------------------------------------------------
    def surfaces(self, hip: FloatArray, primary: SurfacePoint | None) -> list[SurfacePoint]:
        """The surfaces the constraints act on this tick: the perceived one (if any), then walls.

        ``primary`` is the fused surface, or the last one the guard holds after the fusion
        lost it (:class:`~hapticloud.core.haptics.unknown.SurfaceGuard`).
        """
        out: list[SurfacePoint] = [] if primary is None else [primary]
        # A wall's own point serves as its centroid: (h - p) . n is the same for every point p of
        # the plane, and nothing else reads the centroid. Built once, in __init__.
        out.extend(self._wall_surfaces)
        return out

    def tick(
        self,
        t: float,
        q: ArrayLike,
        qd: ArrayLike,
        *,
        interaction_torque: ArrayLike | None = None,
        fused: FusedSurface | None = None,
    ) -> TickResult:
        """One control tick at time ``t`` (s) for the measured joint state ``q``, ``qd``.

        Parameters
        ----------
        t
            Time (s) at which the fusion is sampled (same clock as the estimates').
        q, qd
            Joint positions (rad) and velocities (rad/s), shape ``(n,)``.
        interaction_torque
            ``J^T f`` of the handle force sensor (N m), or ``None`` without a sensor.
        fused
            A fused surface to use instead of sampling the loop's fusion (e.g. replay, or the
            control process's). An invalid one (or none from a loop with a fusion) leaves the
            space unknown: the guard holds the last surface, then stops (:attr:`guard`).

        Returns
        -------
        TickResult
        """
        t0 = time.perf_counter()
        hip = self._hip_state(q, qd)
        primary, hold_q, space, fused_ok = self._space_around(t, hip, fused)
        tau_int = None if interaction_torque is None else np.asarray(interaction_torque, float)
        n_haptic, present, factor, normals, d_min, approach, nearest = self._surface_rows(
            hip, primary
        )
        qdd5 = self._level5_acceleration(hip, hold_q, tau_int, factor)
        m = n_haptic
        unknown = self.config.unknown
        if space is SpaceState.HOLDING and primary is not None and d_min > unknown.lateral_beyond_m:
            # A held plane says nothing of what lies beside it: away from it the HIP's speed
            # along it is capped (the tangential rows, their target limited; _tangential_rows).
            held = normals if normals else [np.asarray(primary.normal, dtype=np.float64)]
            m = self._tangential_rows(hip.jacobian, held, qdd5, m, hip.qd, unknown.lateral_m_s)
        elif normals and self.config.frictionless:
            m = self._tangential_rows(hip.jacobian, normals, qdd5, m)
        self._rows_written = m
        out = self._control(hip, qdd5, tau_int, hold_q, m, n_haptic)
        self._n_haptic = n_haptic
        self._last_x = (out.qdd, out.tau)
        violation = float(out.level_slack[3])
        if not math.isfinite(violation):
            violation = 0.0
        return TickResult(
            out.tau,
            out.qdd,
            out.status,
            d_min + self.config.clearance_m,
            approach,
            nearest,
            present & (POSITIONAL | VELOCITY | FORCE),
            violation,
            fused_ok,
            out.solve_us,
            out.step_us,
            (time.perf_counter() - t0) * 1e6,
            out.clamped,
            space,
        )

    def _hip_state(self, q: ArrayLike, qd: ArrayLike) -> HipState:
        """``robot.update(q, qd)`` and the HIP's state, its sphere grown by the clearance.

        :meth:`HipState.from_model` without re-checking the radius (checked once, in __init__).
        The constraints keep the HIP sphere grown by the clearance out of the surface: the fused
        surface is ~0.5 mm off at contact, which the radius alone would let through.
        """
        robot = self.robot
        robot.update(q, qd)
        if self._trusted:  # the shipped model hands its terms out in one call
            return HipState(*robot.hip_terms(), self.hip_radius_m + self.config.clearance_m)
        return HipState(
            robot.hip_position(),
            robot.qd,
            robot.hip_jacobian(),
            robot.hip_jdot_qd(),
            robot.mass_matrix(),
            robot.nonlinear_effects(),
            self.hip_radius_m + self.config.clearance_m,
        )

    def _space_around(
        self, t: float, hip: HipState, fused: FusedSurface | None
    ) -> tuple[SurfacePoint | None, FloatArray | None, SpaceState, bool]:
        """What the tick knows of the space around the HIP: ``(surface, hold_q, state,
        fused_ok)``, the surface the constraints act on (the fused one, the one the guard holds,
        or none), the joint position to hold while stopped, the :class:`SpaceState`, and whether
        the fusion gave a valid surface. Sets :attr:`last_fused` and this tick's approach-speed
        cap (:attr:`approach_limit_mps`, tightened by the guard). Plain tuples on the hot path:
        a named tuple's construction costs more than the rest of a free tick's bookkeeping."""
        perceived = fused is not None or self.fusion is not None
        if fused is None and self.fusion is not None:
            fused = self.fusion.sample(t)
        self.last_fused = fused
        fused_ok = fused is not None and fused.valid
        self._cap = self.approach_limit_mps
        if not perceived:
            return None, None, SpaceState.KNOWN, fused_ok
        known, age = None, 0.0
        if fused_ok:
            centroid, normal, velocity = fused.centroid, fused.normal, fused.velocity
            if type(fused) is not FusedSurface:  # the fusion's own are float arrays already
                centroid, normal = _float_array(centroid), _float_array(normal)
                velocity = _float_array(velocity)
            known = SurfacePoint(centroid, normal, velocity, self.fused_region)
            age = fused.age_s
        why, free = "no fused surface", False
        if fused is not None and known is None:
            why = fused.reason
            free = free_proof_holds(
                getattr(fused, "free_m", 0.0),
                getattr(fused, "free_hip", None),
                hip.position,
                hip.radius_m,
                self.config.unknown,
            )
        decision = self.guard.step(t, known, self.robot.q, why, free, age)
        cap = decision.approach_limit_mps
        if cap is not None and (self._cap is None or cap < self._cap):
            self._cap = cap
        return decision.surface, decision.hold_q, decision.state, fused_ok

    def _surface_rows(
        self, hip: HipState, primary: SurfacePoint | None
    ) -> tuple[int, int, FloatArray | None, list[FloatArray], float, float, int]:
        """Each surface's rows into the buffer: the shared motion row (positional and velocity,
        :meth:`_motion_bound`) and the force row, from the constraints' kernels.

        Returns ``(n_rows, present, factor, normals, d_min, approach, nearest)``: the rows
        written, their kind bits or-ed, the Cholesky factor of ``M`` if a force row needed it,
        the normals of the surfaces in reach, and the nearest surface's free distance (m, the
        clearance included), approach speed (m/s) and index (:attr:`TickResult.nearest`).
        """
        cfg = self.config
        n = self.n_joints
        G, hv, kind = self._G, self._h, self._kind
        if self._rows_written:
            G[: self._rows_written] = 0.0  # rows are written sparsely below; clear last tick's
        m = present = 0
        factor = None
        normals: list[FloatArray] = []
        d_min, approach, nearest = math.inf, 0.0, -1
        ff_v = cfg.velocity.surface_velocity_feedforward
        force_reach = cfg.force.activation_distance_m if cfg.force_enabled else -math.inf
        first = 0 if primary is not None else 1
        for i, surface in enumerate(self.surfaces(hip.position, primary)):
            hs = trusted_haptic_state(hip, surface)
            if not math.isfinite(hs.d_proj + hs.Jdc_qd + hs.d_dot_robot + hs.d_dot_surface):
                hs = haptic_state(hip, surface)  # names the culprit
            d = hs.d_proj
            if d < d_min:
                d_min, nearest = d, i + first
                approach = -hs.distance_rate(ff_v)
            if d > self._act_motion and not d <= force_reach:
                continue
            normals.append(hs.normal)
            bound, bits = self._motion_bound(hs)
            if bits:
                np.negative(hs.J_c, out=G[m, :n])
                hv[m] = bound
                kind[m] = bits
                present |= bits
                m += 1
            if d <= force_reach:
                if factor is None:
                    factor = mass_factor(hip.mass_matrix, "mass_matrix")
                limit = self._force_limit[surface.body_region]
                w, hv[m] = self.force.bound(hs, factor, hip.nonlinear_effects, limit)
                np.negative(w, out=G[m, n:])
                kind[m] = FORCE
                present |= FORCE
                m += 1
        return m, present, factor, normals, d_min, approach, nearest

    def _level5_acceleration(
        self,
        hip: HipState,
        hold_q: FloatArray | None,
        tau_int: FloatArray | None,
        factor: FloatArray | None,
    ) -> FloatArray | None:
        """The level-5 optimum's accelerations: what the robot does where no constraint binds
        (``None`` for zero: transparent without a measured push)."""
        cfg = self.config
        if hold_q is not None:
            return hold_acceleration(self.robot.q, hip.qd, hold_q, cfg.unknown)
        ctrl_cfg = self.controller.config
        if not cfg.transparent:
            return -ctrl_cfg.min_acceleration.damping_1_per_s * hip.qd
        if tau_int is None:
            return None
        if factor is None:
            factor = mass_factor(hip.mass_matrix, "mass_matrix")
        # tau = h leaves M qdd = tau_int: the free acceleration of the patient's push.
        scale = ctrl_cfg.equation_of_motion.interaction_torque_scale
        qdd5, _ = lapack.dpotrs(factor, scale * tau_int, lower=False)
        return qdd5

    def _control(
        self,
        hip: HipState,
        qdd5: FloatArray | None,
        tau_int: FloatArray | None,
        hold_q: FloatArray | None,
        m: int,
        n_haptic: int,
    ) -> ControlOutput:
        """The controller's answer for the ``m`` rows in the buffer: the exact shortcut's, or the
        solve's (:meth:`~HierarchicalController.step_trusted` for the shipped model's state)."""
        cfg = self.config
        transparent = cfg.transparent and hold_q is None
        # In a contact the solver is needed tick after tick: while the last tick needed it and
        # haptic rows are still there, skip the shortcut's check (~5-15 µs) and solve directly.
        try_shortcut = cfg.exact_shortcut and not (self._solved_last and n_haptic)
        out = self._shortcut(hip, qdd5, tau_int, m, transparent) if try_shortcut else None
        if out is not None:
            self._solved_last = False
            return out
        rows = [Inequality(self._G[:m], self._h[:m], "haptic")] if m else []
        if hold_q is not None:
            motion: Equality | None = Equality(self._a_hold, qdd5, "position hold")
        elif transparent:
            motion = Equality(self._a_tau, hip.nonlinear_effects, "transparency")
        else:
            motion = None
        # The controller's step without re-converting what the robot model validated (float
        # arrays of the right shapes, dt checked in __init__); its checks on values stay.
        step = self.controller.step_trusted if self._trusted else self._step_public
        robot = self.robot
        inputs = StepInputs(
            robot.q,
            robot.qd,
            hip.mass_matrix,
            hip.nonlinear_effects,
            self.dt,
            hip.position,
            hip.jacobian,
            hip.jdot_qd,
            rows,
            (),
            motion,
            tau_int,
        )
        out = step(time.perf_counter(), inputs)
        # Relaxed: a constraint bound (level 5 gave way), so the next tick likely solves too.
        self._solved_last = out.status is not ControlStatus.OK
        return out

    def _step_public(self, t0: float, inputs: StepInputs) -> ControlOutput:
        """The controller's checked :meth:`~HierarchicalController.step`, for any other robot."""
        return self.controller.step(
            inputs.q,
            inputs.qd,
            inputs.M,
            inputs.h,
            inputs.dt,
            hip_position=inputs.hip_position,
            hip_jacobian=inputs.hip_jacobian,
            hip_jdot_qd=inputs.hip_jdot_qd,
            haptic_rows=inputs.haptic_rows,
            wall_rows=inputs.wall_rows,
            motion=inputs.motion,
            interaction_torque=inputs.interaction_torque,
        )

    def _shortcut(
        self,
        hip: HipState,
        qdd5: FloatArray | None,
        tau_int: FloatArray | None,
        m: int,
        transparent: bool,
    ) -> ControlOutput | None:
        """The controller's answer without solving, when it is the level-5 optimum; else None.

        Level 5 alone fixes ``x`` (with the equation of motion): ``tau = h`` (transparent; then
        ``qdd = M^-1 tau_int``) or ``qdd = -D qd`` (minimum accelerations). If that ``x`` already
        meets every inequality of levels 1-4 (torque limits, joint position and velocity limits,
        fixed walls, the haptic rows), it is the hierarchy's unique optimum: every level holds
        exactly, so the solver would return it too (``tests/core/test_loop.py`` checks both agree).
        Most ticks are of this kind (free motion, or constraints present but not binding); it
        saves the ~100 µs of the solve on them. ``step_us`` of its output is the check's time,
        ``solve_us`` is 0.
        """
        t0 = time.perf_counter()
        ctrl = self.controller
        if self._limits_for is not ctrl:
            self._limits, self._limits_for = ctrl.limit_check(self.dt, _SHORTCUT_TOL), ctrl
        qd = hip.qd
        M, h = hip.mass_matrix, hip.nonlinear_effects
        qdd = np.zeros(self.n_joints) if qdd5 is None else qdd5
        if transparent:
            tau = h.copy()
        else:
            tau = M.dot(qdd) + h
            if tau_int is not None:
                tau -= ctrl.config.equation_of_motion.interaction_torque_scale * tau_int
        if not finite_total((qdd, tau)):
            return None  # the controller reports the fault
        x = np.concatenate((qdd, tau))
        # The haptic rows first: in contact they are the ones that fail, and they are built.
        # The comparisons run on Python floats: a handful of numbers, where each numpy call
        # (~1 us with the wrappers) would cost more than the arithmetic; the bounds are the same
        # IEEE operations in the same order, so every decision is the one numpy would make.
        if m:
            tol = _SHORTCUT_TOL
            for gx, hj in zip(self._G[:m].dot(x).tolist(), self._h[:m].tolist(), strict=True):
                if gx > hj + tol * (1.0 + abs(hj)):
                    return None
        # Levels 1-2 checked from the tasks' definitions, joint by joint (cheaper than building
        # their rows); then each fixed wall's rows.
        if not self._limits.admits(tau.tolist(), self.robot.q.tolist(), qd.tolist(), qdd.tolist()):
            return None
        if ctrl.walls is not None:
            w = ctrl.walls.rows(hip.position, hip.jacobian, hip.jdot_qd, qd, self.dt)
            if w.h.shape[0] and or_reduce(w.G @ x > w.h + _SHORTCUT_TOL * (1.0 + np.abs(w.h))):
                return None
        return ControlOutput(
            tau,
            qdd.copy(),
            ControlStatus.OK,
            np.zeros(len(LEVEL_NAMES)),
            0.0,
            False,
            (time.perf_counter() - t0) * 1e6,
            "",
        )

    def last_binding(self) -> int:
        """Which constraints bound the last tick's solution (bits as ``TickResult.rows``).

        A row binds when ``G x >= h - tol``. Evaluated on demand, outside the timed tick: it is
        telemetry, not control.
        """
        n = self.n_joints
        m = self._n_haptic
        if not m or self._last_x is None:
            return 0
        qdd, tau = self._last_x
        G, hv, kind = self._G, self._h, self._kind
        gx = G[:m, :n] @ qdd + G[:m, n:] @ tau
        binding = 0
        for j in range(m):
            bound = hv[j]
            if gx[j] >= bound - BINDING_TOL * max(1.0, abs(bound)):
                k = kind[j]
                if k & _TIGHTER:  # a shared row: credit the constraint that set its bound
                    k = POSITIONAL if k & _POS_TIGHTER else VELOCITY
                binding |= k
        return binding & (POSITIONAL | VELOCITY | FORCE)

    def _motion_bound(self, hs: HapticState) -> tuple[float, int]:
        """Right-hand side of the shared ``[-J_c, 0]`` row and which constraints it holds.

        The bits are those of the constraints with rows; the tighter one is marked with
        ``_TIGHTER`` so that a binding row is credited to it alone.
        """
        cfg = self.config
        dt = self.dt
        d = hs.d_proj
        bound, bits, which = math.inf, 0, 0
        if cfg.positional_enabled and d <= cfg.positional.activation_distance_m:
            bound = self.positional.bound(hs, dt)
            bits, which = POSITIONAL, POSITIONAL
        if cfg.velocity_enabled and d <= cfg.velocity.activation_distance_m:
            b_v = self.velocity.bound(hs, dt)
            bits |= VELOCITY
            if b_v < bound:
                bound, which = b_v, VELOCITY
        cap = self._cap
        if cap is not None:
            b_c = self.velocity.bound(hs, dt, max(cap, 0.0))
            bits |= VELOCITY
            if b_c < bound:
                bound, which = b_c, VELOCITY
        if bits == POSITIONAL | VELOCITY:
            # Both rows present: the binding one is the tighter (``which``).
            bits |= _TIGHTER | (_POS_TIGHTER if which == POSITIONAL else 0)
        return bound, bits

    def _tangential_rows(
        self,
        J: FloatArray,
        normals: list[FloatArray],
        qdd5: FloatArray | None,
        m: int,
        qd: FloatArray | None = None,
        speed_cap_mps: float | None = None,
    ) -> int:
        """Rows holding the HIP's acceleration across the active normals at level 5's one.

        Why: the constraints bound the HIP's acceleration along ``n`` only; the hierarchy then
        meets them with the smallest change of the level-5 torques, which in joint space also
        accelerates the HIP *along* the surface (by ``J M^-2 J^T n``: the arm's inertia is far
        from isotropic), so the HIP slid ~10 cm up the head on every impact. Holding the
        tangential acceleration at level 5's one (``qdd5``; with ``tau = h`` that is the
        patient's push alone; ``None`` for zero) leaves the constraints changing the HIP's
        acceleration along the normal only, as a frictionless contact on a point mass would
        (a normal force on the arm itself would still turn it sideways: its task-space inertia
        is anisotropic). Each tangent ``t`` gives
        the pair ``t^T J qdd <= a_t + b`` and ``-t^T J qdd <= b - a_t`` (a band of half-width
        ``b = TANGENT_BAND_M_S2`` the haptic level can hold): rows ``t^T J`` then ``-t^T J``.

        ``speed_cap_mps`` (with ``qd``), while a surface is held away from it: the target along
        each tangent is the push's, but none that takes the HIP's speed along that tangent past
        the cap within the velocity constraint's horizon ``kv dt``. Why: the held plane bounds
        the approach toward the body the last estimate saw, and nothing beside it. Measured
        (``bench safety``, perception at 7 Hz and 146 ms, with better estimates at the torso's
        edge): holding tick after tick, the patient pushed the HIP sideways at 0.6-0.7 m/s, 84 mm
        in 144 ms, from the torso's plane into the head, which no estimate had shown yet. The
        distance to the patient changes at most as fast as the HIP moves. (A cap in contact too,
        or a row along the lateral velocity instead of the tangential rows, made seed sweeps of
        other cells UNSAFE; docs/benchmarks.md.) Returns the new row count.
        """
        n = self.n_joints
        if len(normals) == 1:
            tangents = _tangents(normals[0])
        else:
            # The directions across every active normal: the null space of their stack.
            _, sv, vt = np.linalg.svd(np.array(normals))
            rank = int(np.count_nonzero(sv > 1e-3))
            tangents = vt[rank:]
        if not len(tangents):
            return m
        k = tangents.shape[0]
        gs = tangents.dot(J)
        G, hv, kind = self._G, self._h, self._kind
        G[m : m + k, :n] = gs
        G[m + k : m + 2 * k, :n] = -gs  # cheaper than np.negative(out=) into a strided view
        # A band of +-TANGENT_BAND around the free acceleration, not an exact equality: two
        # opposite rows with equal bounds are degenerate for DAQP, which then failed now and then
        # (3 ticks in the wall scene) and fell back to the 1.5 ms cascade.
        if qdd5 is None and speed_cap_mps is None:
            hv[m : m + 2 * k] = TANGENT_BAND_M_S2
        else:
            # Both bounds from Python floats in one assignment: a sum or difference of two
            # doubles rounds the same in Python as in numpy, and this saves two ufunc calls.
            a = [0.0] * k if qdd5 is None else gs.dot(qdd5).tolist()
            if speed_cap_mps is not None and qd is not None:
                # While a surface is held: the push's acceleration along each tangent, but none
                # that takes the speed along it past the cap within the velocity constraint's
                # horizon (and back under it when above).
                gain_time = self.velocity.config.kv * self.dt
                cap = max(speed_cap_mps, 0.0)
                for i, v in enumerate(gs.dot(qd).tolist()):
                    a[i] = min(max(a[i], (-cap - v) / gain_time), (cap - v) / gain_time)
            band = TANGENT_BAND_M_S2
            hv[m : m + 2 * k] = [ai + band for ai in a] + [band - ai for ai in a]
        kind[m : m + 2 * k] = [0] * (2 * k)
        return m + 2 * k


def _float_array(value: ArrayLike) -> FloatArray:
    """``value`` as a float64 array (itself when it already is one)."""
    return np.asarray(value, dtype=np.float64)


def _tangents(normal: FloatArray) -> FloatArray:
    """Two unit vectors spanning the plane orthogonal to the unit ``normal``, shape (2, 3)."""
    # Cross with the world axis least aligned with n (never parallel, so never ~zero); written
    # out because np.cross costs ~20 µs per call in a 1.25 ms tick.
    x, y, z = float(normal[0]), float(normal[1]), float(normal[2])
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax <= ay and ax <= az:  # n x e_x
        t1 = (0.0, z, -y)
    elif ay <= az:  # n x e_y
        t1 = (-z, 0.0, x)
    else:  # n x e_z
        t1 = (y, -x, 0.0)
    norm = math.sqrt(t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2])
    a, b, c = t1[0] / norm, t1[1] / norm, t1[2] / norm
    return np.array([[a, b, c], [y * c - z * b, z * a - x * c, x * b - y * a]])


def is_fallback(est: SurfaceEstimate) -> bool:
    """True when the curvature-aware estimator fell back to the paper's shells for this estimate.

    It does so when its own fit failed (too few points around the closest point, the closest
    point too far from the data): exactly the estimates that were 5-85 mm off in the impact
    scene, while the same frames' other camera was within 0.5 mm.
    """
    return est.method == "quadric" and len(est.shells) > 0


def admit(est: SurfaceEstimate, min_quality: float, fuse_fallbacks: bool = False) -> bool:
    """Whether a camera's estimate goes to the fusion.

    Valid, of quality >= ``min_quality``, and (unless ``fuse_fallbacks``) not a fallback of the
    curvature estimator (:func:`is_fallback`); or invalid with a proof of free space
    (``free_m`` > 0), which the fusion keeps apart from its surface window. The regression
    weighs samples by age only, so a bad sample moves the fused surface; keeping it out is the
    cheaper remedy, and the other camera usually sees what this one does not.
    """
    if not est.valid:
        return est.free_m > 0.0  # an empty workspace seen is knowledge too (free space)
    if est.quality < min_quality:
        return False
    return fuse_fallbacks or not is_fallback(est)


def build_controller(
    robot: Any,
    config: Any,
    walls: Sequence[Wall],
) -> HierarchicalController:
    """The hierarchical controller of ``robot`` with the ``fixed`` walls at level 3."""
    fixed = [w for w in walls if w.level == "fixed"]
    kwargs: dict[str, Any] = {}
    if fixed:
        kwargs["wall_points"] = np.array([w.point for w in fixed])
        kwargs["wall_normals"] = np.array([w.normal for w in fixed])
    return HierarchicalController.from_robot(robot, config, **kwargs)


__all__ = [
    "BINDING_TOL",
    "FORCE",
    "POSITIONAL",
    "VELOCITY",
    "HapticLoop",
    "HapticsConfig",
    "TickResult",
    "Wall",
    "admit",
    "build_controller",
    "is_fallback",
]
