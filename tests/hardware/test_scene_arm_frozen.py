"""The emulated arm's plant with ``frozen_dynamics`` (configuration terms once per period) against
the exact form, on the demo scene's patient."""

from __future__ import annotations

import numpy as np
from hapticloud.core.robot.model import RobotModel
from hapticloud.hardware.drives.scene_arm import SceneArmFactory


def _hip_path(frozen: bool, ticks: int) -> np.ndarray:
    """The demo's emulated arm under a joint PD on its start posture with gravity compensated:
    the patient's intent moves the hand."""
    arm = SceneArmFactory("demo", frozen_dynamics=frozen)(RobotModel.load())
    assert arm.plant.frozen_dynamics is frozen
    model = RobotModel.load()
    q, qd = arm.plant.q.copy(), arm.plant.qd.copy()
    q_ref, hips = q.copy(), []
    for _ in range(ticks):
        model.update(q, qd)
        tau = model.nonlinear_effects() + 20.0 * (q_ref - q) - 2.0 * qd
        q, qd = arm(q, qd, tau, 1.0 / 800.0)
        hips.append(arm.hip)
    return np.array(hips)


def test_frozen_dynamics_follows_the_exact_plant_within_20_um() -> None:
    exact, frozen = _hip_path(False, 2400), _hip_path(True, 2400)
    travel = np.linalg.norm(np.diff(exact, axis=0), axis=1).sum()
    assert travel > 0.05  # the patient moved the hand: the comparison means something
    assert np.isfinite(frozen).all()
    assert np.abs(frozen - exact).max() < 20e-6
    assert np.abs(frozen - exact).max() > 0.0  # a different integrator, not the same code path
