"""The exoskeleton's rigid-body model: kinematics and dynamics at the HIP, wrapped around Pinocchio.

One :class:`RobotModel` holds the Pinocchio model of the URDF and three ``Data`` work spaces:
one for the controller's per-tick state (:meth:`RobotModel.update` and the accessors), one for
the simulator (:meth:`RobotModel.forward_dynamics`) and one for geometry
(:meth:`RobotModel.link_capsules`), so that a simulator step or a perception crop never
overwrites what the controller reads.

A model object is not thread-safe; a process with several threads gives each one its own model.

Example
-------
>>> model = RobotModel.load()
>>> model.update(model.q_home, np.zeros(model.n_joints))
>>> model.hip_jacobian().shape
(3, 6)
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pinocchio as pin
from hapticloud.assets import asset_path
from numpy.typing import ArrayLike, NDArray

from ..errors import ConfigError, InputError
from ..geometry import Capsule
from ..validation import read_only

FloatArray = NDArray[np.float64]

_FLOAT64 = np.dtype(np.float64)

#: Home configuration of the shipped ANYexo-like model (rad): girdle neutral, upper arm slightly
#: forward and out, forearm turned in, elbow at about 100 deg, so the hand rests in front of the
#: right side of the chest (HIP near (0.28, 0.13, 0.93) m in the world frame).
HOME_CONFIGURATION: Mapping[str, float] = {
    "shoulder_elevation": 0.0,
    "shoulder_protraction": 0.0,
    "shoulder_flexion": 0.35,
    "shoulder_abduction": 0.10,
    "shoulder_internal_rotation": 0.50,
    "elbow_flexion": 1.75,
}


class JointLimits(NamedTuple):
    """Per-joint limits from the URDF, in joint order (read-only arrays).

    ``q_min``, ``q_max`` in rad; ``v_max`` in rad/s; ``tau_max`` in N m (symmetric: ``|tau| <=
    tau_max``).
    """

    q_min: FloatArray
    q_max: FloatArray
    v_max: FloatArray
    tau_max: FloatArray


class LinkCapsule(NamedTuple):
    """One collision primitive of a link as a capsule in that link's frame.

    ``a`` and ``b`` (3,) are the ends of the capsule's axis segment in the link frame (m);
    ``radius_m`` its radius. A URDF cylinder becomes the capsule on its axis segment (so the
    capsule is longer than the cylinder by one radius at each end: a conservative crop); a URDF
    sphere becomes a capsule with ``a == b``. ``name`` is the URDF collision name; ``guided`` is
    True for the patient's arm and hand strapped into the robot (collision names ``guided_*``).
    """

    link: str
    name: str
    radius_m: float
    a: FloatArray
    b: FloatArray
    guided: bool


def default_urdf_path() -> Path:
    """Path of the shipped ANYexo-like URDF (``hapticloud.assets/robot/anyexo.urdf``)."""
    return asset_path("robot", "anyexo.urdf")


def _rpy_matrix(roll: float, pitch: float, yaw: float) -> FloatArray:
    """URDF fixed-axis roll-pitch-yaw: ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _floats(text: str | None, count: int, where: str) -> list[float]:
    if text is None:
        return [0.0] * count
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        raise ConfigError(f"{where}: expected {count} numbers, got {text!r}") from None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"{where}: expected {count} finite numbers, got {text!r}")
    return values


def parse_link_capsules(urdf_text: str, source: str = "URDF") -> tuple[LinkCapsule, ...]:
    """Every collision cylinder and sphere of a URDF as a :class:`LinkCapsule` (link frame).

    Boxes and meshes are not primitives the crop understands and raise :class:`ConfigError`,
    so that a geometry silently missing from the crop cannot happen.
    """
    try:
        root = ET.fromstring(urdf_text)
    except ET.ParseError as err:
        raise ConfigError(f"{source}: not valid XML ({err})") from None
    out: list[LinkCapsule] = []
    for link in root.iter("link"):
        link_name = link.get("name", "")
        for k, coll in enumerate(link.findall("collision")):
            name = coll.get("name") or f"{link_name}_collision_{k}"
            where = f"{source}: link {link_name!r} collision {name!r}"
            origin = coll.find("origin")
            xyz = np.array(_floats(None if origin is None else origin.get("xyz"), 3, where))
            rpy = _floats(None if origin is None else origin.get("rpy"), 3, where)
            geometry = coll.find("geometry")
            shape = None if geometry is None or len(geometry) == 0 else geometry[0]
            if shape is None:
                raise ConfigError(f"{where}: has no geometry")
            if shape.tag not in ("cylinder", "sphere"):
                raise ConfigError(
                    f"{where}: geometry {shape.tag!r} is not supported (use cylinder or sphere)"
                )
            radius = _floats(shape.get("radius"), 1, f"{where} radius")[0]
            if radius <= 0:
                raise ConfigError(f"{where}: radius must be positive, got {radius}")
            if shape.tag == "cylinder":
                length = _floats(shape.get("length"), 1, f"{where} length")[0]
                if length < 0:
                    raise ConfigError(f"{where}: length must be >= 0, got {length}")
                half_axis = _rpy_matrix(*rpy)[:, 2] * (0.5 * length)
                a, b = xyz - half_axis, xyz + half_axis
            else:
                a, b = xyz.copy(), xyz.copy()
            out.append(
                LinkCapsule(
                    link_name, name, radius, read_only(a), read_only(b), name.startswith("guided")
                )
            )
    return tuple(out)


class RobotModel:
    """Rigid-body model of the exoskeleton with the quantities the controller needs at the HIP.

    Build with :meth:`load`. Call :meth:`update` once per control tick with the measured joint
    state; the accessors then return cached read-only arrays computed by that call (frame
    ``LOCAL_WORLD_ALIGNED``: world axes, origin at the HIP). After construction the model is
    updated at the home configuration at rest, so the accessors are always defined.
    """

    def __init__(
        self,
        pin_model: pin.Model,
        capsules: tuple[LinkCapsule, ...],
        *,
        hip_frame: str = "hip",
        source: str = "",
        home: Mapping[str, float] | None = None,
    ) -> None:
        self._model = pin_model
        self._source = source
        if not pin_model.existFrame(hip_frame):
            raise ConfigError(f"{source or 'robot model'}: has no frame {hip_frame!r} for the HIP")
        if pin_model.nq != pin_model.nv or pin_model.nv == 0:
            raise ConfigError(
                f"{source or 'robot model'}: needs revolute/prismatic joints only "
                f"(nq={pin_model.nq}, nv={pin_model.nv})"
            )
        self._hip_id = pin_model.getFrameId(hip_frame)
        self._n = int(pin_model.nv)
        self._joint_names = tuple(str(name) for name in list(pin_model.names)[1:])
        limits = JointLimits(
            read_only(np.array(pin_model.lowerPositionLimit, dtype=np.float64)),
            read_only(np.array(pin_model.upperPositionLimit, dtype=np.float64)),
            read_only(np.array(pin_model.velocityLimit, dtype=np.float64)),
            read_only(np.array(pin_model.effortLimit, dtype=np.float64)),
        )
        for i, name in enumerate(self._joint_names):
            ok = (
                np.isfinite(limits.q_min[i])
                and np.isfinite(limits.q_max[i])
                and limits.q_min[i] < limits.q_max[i]
                and limits.v_max[i] > 0
                and limits.tau_max[i] > 0
            )
            if not ok:
                raise ConfigError(
                    f"{source or 'robot model'}: joint {name!r} needs finite position limits "
                    "lower < upper and positive velocity and effort limits"
                )
        self._limits = limits
        self._capsules = capsules
        self._capsule_frames = []
        for cap in capsules:
            if not pin_model.existFrame(cap.link, pin.BODY):
                raise ConfigError(f"{source or 'robot model'}: no link {cap.link!r} for {cap.name}")
            self._capsule_frames.append(pin_model.getFrameId(cap.link, pin.BODY))
        self._q_home = read_only(self._home_from(home or HOME_CONFIGURATION))

        self._data = pin_model.createData()
        self._data_sim = pin_model.createData()
        self._data_geo = pin_model.createData()
        self._zero = np.zeros(self._n)
        self._shape = (self._n,)
        self._lower_mask = np.tri(self._n, k=-1, dtype=bool)
        self.update(self._q_home, self._zero)

    # ----- construction ------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path | None = None, *, hip_frame: str = "hip") -> RobotModel:
        """Load a URDF (default: the shipped ANYexo-like model).

        Parameters
        ----------
        path
            URDF file; ``None`` loads ``hapticloud.assets/robot/anyexo.urdf``.
        hip_frame
            Name of the frame (URDF link) that is the haptic interaction point.

        Raises
        ------
        ConfigError
            If the file is missing or not a usable URDF (names the file and what is wrong).
        """
        urdf = default_urdf_path() if path is None else Path(path)
        try:
            text = urdf.read_text()
        except FileNotFoundError:
            raise ConfigError(f"{urdf}: no such file") from None
        capsules = parse_link_capsules(text, str(urdf))
        try:
            pin_model = pin.buildModelFromXML(text)
        except (RuntimeError, ValueError) as err:
            raise ConfigError(f"{urdf}: not a usable URDF ({err})") from None
        home = HOME_CONFIGURATION if path is None else None
        return cls(pin_model, capsules, hip_frame=hip_frame, source=str(urdf), home=home)

    def _home_from(self, home: Mapping[str, float]) -> FloatArray:
        # A URDF of another robot has no home here: take the configuration closest to zero.
        q = np.array([float(home.get(name, 0.0)) for name in self._joint_names])
        return np.clip(q, self._limits.q_min, self._limits.q_max)

    # ----- static properties -------------------------------------------------------------------
    @property
    def n_joints(self) -> int:
        """Number of actuated joints (the size of ``q``, ``qd``, ``tau``)."""
        return self._n

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Joint names in the order of ``q``."""
        return self._joint_names

    @property
    def limits(self) -> JointLimits:
        """Position, velocity and effort limits parsed from the URDF."""
        return self._limits

    @property
    def q_min(self) -> FloatArray:
        """Lower joint position limits (rad)."""
        return self._limits.q_min

    @property
    def q_max(self) -> FloatArray:
        """Upper joint position limits (rad)."""
        return self._limits.q_max

    @property
    def v_max(self) -> FloatArray:
        """Joint speed limits (rad/s)."""
        return self._limits.v_max

    @property
    def tau_max(self) -> FloatArray:
        """Joint torque limits (N m), symmetric."""
        return self._limits.tau_max

    @property
    def q_home(self) -> FloatArray:
        """Home configuration (rad): hand in front of the chest."""
        return self._q_home

    @property
    def capsule_specs(self) -> tuple[LinkCapsule, ...]:
        """Collision primitives per link, as capsules in the link frames (URDF order)."""
        return self._capsules

    @property
    def pin_model(self) -> pin.Model:
        """The underlying Pinocchio model (do not modify)."""
        return self._model

    @property
    def source(self) -> str:
        """The URDF this model was loaded from."""
        return self._source

    # ----- per-tick state ----------------------------------------------------------------------
    def _joint_vector(self, value: ArrayLike, name: str) -> FloatArray:
        if type(value) is np.ndarray and value.dtype is _FLOAT64 and value.shape == self._shape:
            arr = value  # the per-tick case: nothing to convert
        else:
            arr = np.asarray(value, dtype=np.float64)
            if arr.shape != (self._n,):
                raise InputError(f"{name}: expected shape ({self._n},), got {np.shape(value)}")
        # A finite sum proves every entry finite (cheaper than isfinite + all); a finite vector
        # whose sum overflows gets the exact check.
        if not math.isfinite(sum(arr.tolist())) and not np.isfinite(arr).all():
            raise InputError(f"{name}: must be finite, got {arr.tolist()}")
        return arr

    def update(self, q: ArrayLike, qd: ArrayLike) -> None:
        """Compute every per-state quantity once for joint positions ``q`` (rad) and ``qd`` (rad/s).

        Runs forward kinematics with ``qdd = 0`` (so the frame's classical acceleration is
        ``Jdot qd``), the joint Jacobians, the frame placements, CRBA and the nonlinear effects.

        Raises
        ------
        InputError
            If ``q`` or ``qd`` is not a finite vector of ``n_joints`` numbers.
        """
        shape = self._shape
        if (
            type(q) is np.ndarray
            and type(qd) is np.ndarray
            and q.dtype is _FLOAT64
            and qd.dtype is _FLOAT64
            and q.shape == shape
            and qd.shape == shape
            # A finite sum proves every entry finite (NaN and inf propagate, quietly, in Python
            # floats); cheaper than isfinite + all. An overflow takes the exact checks below.
            and math.isfinite(sum(q.tolist()) + sum(qd.tolist()))
        ):
            pass  # the per-tick case: finite float vectors of the right shape, nothing to convert
        else:
            q = self._joint_vector(q, "q")
            qd = self._joint_vector(qd, "qd")
        model, data, fid = self._model, self._data, self._hip_id
        pin.forwardKinematics(model, data, q, qd, self._zero)
        pin.computeJointJacobians(model, data)
        # The placement returned is data.oMf[fid]; indexing data.oMf from Python costs ~0.5 us.
        placement = pin.updateFramePlacement(model, data, fid)
        jac = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)[:3]
        acc = pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
        mass = pin.crba(model, data, q).copy()
        # CRBA fills the upper triangle only (copyto buffers the overlapping transpose first).
        np.copyto(mass, mass.T, where=self._lower_mask)
        nle = pin.nonLinearEffects(model, data, q, qd).copy()

        # Written out rather than read_only(): ~0.2 us a call, eight times a tick.
        q = q.copy()
        q.setflags(write=False)
        qd = qd.copy()
        qd.setflags(write=False)
        pos = placement.translation.copy()
        pos.setflags(write=False)
        jac = np.ascontiguousarray(jac)
        jac.setflags(write=False)
        lin = acc.linear.copy()
        lin.setflags(write=False)
        mass.setflags(write=False)
        nle.setflags(write=False)
        self._q, self._qd, self._hip_pos, self._hip_jac = q, qd, pos, jac
        self._hip_acc, self._mass, self._nle = lin, mass, nle
        # J qd only when asked for (the control tick does not read it).
        self._hip_vel: FloatArray | None = None

    @property
    def q(self) -> FloatArray:
        """Joint positions of the last :meth:`update` (rad)."""
        return self._q

    @property
    def qd(self) -> FloatArray:
        """Joint velocities of the last :meth:`update` (rad/s)."""
        return self._qd

    def hip_position(self) -> FloatArray:
        """HIP position in the world frame (m), shape (3,)."""
        return self._hip_pos

    def hip_velocity(self) -> FloatArray:
        """HIP linear velocity in world axes (m/s), shape (3,): ``J qd``."""
        vel = self._hip_vel
        if vel is None:
            vel = self._hip_jac @ self._qd
            vel.setflags(write=False)
            self._hip_vel = vel
        return vel

    def hip_jacobian(self) -> FloatArray:
        """Translational HIP Jacobian (m/rad), shape (3, n), world axes (LOCAL_WORLD_ALIGNED)."""
        return self._hip_jac

    def hip_jdot_qd(self) -> FloatArray:
        """``Jdot qd`` (m/s^2), shape (3,): the HIP's classical acceleration with ``qdd = 0``.

        Classical (not spatial) acceleration, so it includes the centripetal term ``w x v``: the
        second time derivative of :meth:`hip_position` is ``J qdd + hip_jdot_qd()``.
        """
        return self._hip_acc

    def hip_terms(
        self,
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """``(hip_position, qd, hip_jacobian, hip_jdot_qd, mass_matrix, nonlinear_effects)`` of
        the last :meth:`update` in one call (the control tick's ``HipState``, less the radius)."""
        return self._hip_pos, self._qd, self._hip_jac, self._hip_acc, self._mass, self._nle

    def mass_matrix(self) -> FloatArray:
        """Joint-space inertia ``M(q)`` (kg m^2), shape (n, n), symmetric positive definite."""
        return self._mass

    def nonlinear_effects(self) -> FloatArray:
        """``h(q, qd) = C(q, qd) qd + g(q)`` (N m), shape (n,): ``M qdd + h = tau``."""
        return self._nle

    # ----- simulator and geometry --------------------------------------------------------------
    def forward_dynamics(self, q: ArrayLike, qd: ArrayLike, tau: ArrayLike) -> FloatArray:
        """Joint accelerations ``M^-1 (tau - h)`` (rad/s^2) by ABA, for the simulator.

        Uses its own work space: the state of :meth:`update` is untouched.

        Parameters
        ----------
        q, qd, tau
            Joint positions (rad), velocities (rad/s) and torques (N m), each shape (n,).
        """
        q = self._joint_vector(q, "q")
        qd = self._joint_vector(qd, "qd")
        tau = self._joint_vector(tau, "tau")
        return np.array(pin.aba(self._model, self._data_sim, q, qd, tau), dtype=np.float64)

    def link_placements(self, q: ArrayLike) -> dict[str, tuple[FloatArray, FloatArray]]:
        """World pose ``(R (3, 3), p (3,))`` of every link that carries a capsule, at ``q``."""
        q = self._joint_vector(q, "q")
        model, data = self._model, self._data_geo
        pin.forwardKinematics(model, data, q)
        out: dict[str, tuple[FloatArray, FloatArray]] = {}
        for cap, fid in zip(self._capsules, self._capsule_frames, strict=True):
            if cap.link not in out:
                placement = pin.updateFramePlacement(model, data, fid)
                out[cap.link] = (placement.rotation.copy(), placement.translation.copy())
        return out

    def link_capsules(self, q: ArrayLike, *, include_guided: bool = True) -> list[Capsule]:
        """World-frame capsules of every link at ``q``, in the order of :attr:`capsule_specs`.

        Parameters
        ----------
        q
            Joint positions (rad), shape (n,).
        include_guided
            Also return the patient's strapped-in arm and hand (``LinkCapsule.guided``); the
            perception crop wants them, a robot self-collision check would not.
        """
        poses = self.link_placements(q)
        out: list[Capsule] = []
        for cap in self._capsules:
            if cap.guided and not include_guided:
                continue
            rot, pos = poses[cap.link]
            out.append(Capsule(rot @ cap.a + pos, rot @ cap.b + pos, cap.radius_m))
        return out

    def hip_position_at(self, q: ArrayLike) -> FloatArray:
        """HIP position (m) at ``q``, leaving :meth:`update`'s state untouched (tests, tools)."""
        q = self._joint_vector(q, "q")
        pin.forwardKinematics(self._model, self._data_geo, q)
        placement = pin.updateFramePlacement(self._model, self._data_geo, self._hip_id)
        return placement.translation.copy()

    def hip_jacobian_at(self, q: ArrayLike) -> FloatArray:
        """Translational HIP Jacobian (3, n) at ``q`` without touching :meth:`update`'s state."""
        q = self._joint_vector(q, "q")
        jac = pin.computeFrameJacobian(
            self._model, self._data_geo, q, self._hip_id, pin.LOCAL_WORLD_ALIGNED
        )
        return np.array(jac[:3])
