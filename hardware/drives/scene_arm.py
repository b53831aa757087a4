"""The emulated arm of a scene: the exoskeleton as ``hapticloud run`` integrates it, with the
scene's simulated patient pushing the handle.

:class:`SceneArmFactory` is what :class:`~hapticloud.hardware.control.process.ControlProcess`
takes as ``dynamics``: a small picklable object (the scene's name or path and its overrides) that
the drive emulator calls with its robot model, in its own process, to get an
:class:`~.emulator.ArmDynamics`. The scene is built there by the builders the deterministic
simulation uses (:func:`~hapticloud.core.scene.assembly.assemble`,
:func:`~hapticloud.core.sim.closed_loop.build_plant`): the same
:class:`~hapticloud.core.sim.patient.PatientArm` (intent script, muscle spring-damper, posture
torque) and the same :class:`~hapticloud.core.sim.exo.ExoPlant` parameters (substeps, the hand's
mass at the HIP, unmodelled joint friction). Each call of the returned :class:`SceneArm` advances
that plant by ``dt`` with the drives' torques held and the patient's forces applied (``J^T f`` of
the hand force at the HIP, plus the null-space posture torque), from the joint state the emulator
hands in.

The patient's clock is the arm's own: time 0 is the first call and every call advances it by
``dt``. The emulator holds a disabled arm still without calling the dynamics
(``brake_when_disabled``), so the patient's script starts when the drives first apply torque,
i.e. when the session is enabled, not when the process starts. A scene without ``[patient]``
gets :class:`~.emulator.RigidArm` (nobody pushes the handle).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from hapticloud.core.robot.model import RobotModel
from hapticloud.core.scene.assembly import Assembly
from hapticloud.core.sim.exo import ExoPlant
from hapticloud.core.sim.patient import PatientArm
from numpy.typing import NDArray

from .emulator import ArmDynamics, EmulatorConfig, RigidArm

__all__ = ["SceneArm", "SceneArmFactory"]

FloatArray = NDArray[np.float64]


class SceneArm:
    """:class:`~.emulator.ArmDynamics` of the exoskeleton with the scene's patient at the handle.

    Parameters
    ----------
    plant
        The plant to integrate (its joint state is overwritten by each call's ``q``, ``qd``).
    patient
        The patient's arm; its intent is read on the plant's clock (:attr:`t`).
    """

    def __init__(self, plant: ExoPlant, patient: PatientArm) -> None:
        self.plant = plant
        self.patient = patient
        self.calls = 0

    @property
    def t(self) -> float:
        """The patient's clock (s): 0 before the first call, then ``dt`` more per call."""
        return float(self.plant.t)

    @property
    def hip(self) -> FloatArray:
        """The HIP position (m, world) after the last call."""
        return self.plant.model.hip_position().copy()

    @property
    def hand_force(self) -> FloatArray:
        """What the handle's force sensor would read after the last call (N, world)."""
        return self.plant.state().hand_force

    def __call__(
        self, q: FloatArray, qd: FloatArray, tau: FloatArray, dt: float
    ) -> tuple[FloatArray, FloatArray]:
        plant = self.plant
        plant.q = np.array(q, dtype=np.float64)
        plant.qd = np.array(qd, dtype=np.float64)
        plant.dt = float(dt)
        state = plant.step(np.array(tau, dtype=np.float64), self.patient.forces)
        self.calls += 1
        return state.q, state.qd


@dataclass(frozen=True)
class SceneArmFactory:
    """Picklable ``model -> ArmDynamics`` for a scene: :class:`SceneArm` with its patient, or
    :class:`~.emulator.RigidArm` when the scene has none (see the module docstring).

    Parameters
    ----------
    scene
        Scene file or shipped scene name.
    overrides
        ``--set`` style overrides (``{"patient.stiffness_n_per_m": 300.0}``).
    substeps
        Plant integration steps per call; ``None``: the scene's ``loop.substeps``.

    Examples
    --------
    >>> factory = SceneArmFactory("impacts")
    >>> import pickle; pickle.loads(pickle.dumps(factory)) == factory
    True
    """

    scene: str
    overrides: Mapping[str, Any] | None = None
    substeps: int | None = None
    #: The plant's configuration terms once per period (:class:`~hapticloud.core.sim.exo.ExoPlant`'s
    #: ``frozen_dynamics``): 148 instead of 252 µs a period for the demo, the HIP within 16 µm
    #: of the exact form over 10 s and 0.57 m of travel. The emulated arm runs in real time.
    frozen_dynamics: bool = True

    def build(self, model: RobotModel | None = None) -> tuple[ArmDynamics, Assembly]:
        """The dynamics and the scene's :class:`~hapticloud.core.scene.assembly.Assembly` it was
        built from (for its ``q0``, ``hip0``, patient and ground truth)."""
        from hapticloud.core.scene import load_scene
        from hapticloud.core.scene.assembly import assemble
        from hapticloud.core.sim.closed_loop import build_plant

        loaded = load_scene(self.scene, dict(self.overrides) if self.overrides else None)
        if loaded.cameras:
            # Only the patient and the plant are needed here: no rendering cameras.
            names = [c.name for c in loaded.cameras]
            loaded = loaded.with_overrides({f"cameras.{n}.model": "oracle" for n in names})
        parts = assemble(loaded)
        if model is None:
            model = RobotModel.load(loaded.config.robot.urdf or None)
        if parts.patient is None:
            return RigidArm(model, EmulatorConfig().joint_damping_nms), parts
        substeps = None if self.substeps is None else int(self.substeps)
        plant = build_plant(
            loaded,
            model,
            parts.q0,
            held=True,
            substeps=substeps,
            frozen_dynamics=self.frozen_dynamics,
        )
        return SceneArm(plant, parts.patient), parts

    def __call__(self, model: RobotModel) -> ArmDynamics:
        return self.build(model)[0]
