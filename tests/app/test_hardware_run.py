"""``hapticloud run --hardware``: the scene's arm for the drive emulator, and a short real-time
session through the control process (API and command line)."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
from hapticloud.app.cli import main
from hapticloud.core.robot.model import RobotModel
from hapticloud.hardware.drives import RigidArm
from hapticloud.hardware.drives.scene_arm import SceneArm, SceneArmFactory
from hapticloud.hardware.session.run import HARDWARE_MODE, run_session

DT = 1.0 / 800.0
# Oracle cameras: the session's perception costs ~1 ms a frame instead of tens (CI machines).
ORACLE = {"cameras.front.model": "oracle", "cameras.right45.model": "oracle"}


# ----- the scene's arm ---------------------------------------------------------------------------
def _push(arm: SceneArm, q: np.ndarray, ticks: int) -> tuple[np.ndarray, np.ndarray]:
    """Step ``arm`` with gravity compensation only (the controller's transparency, no haptics)."""
    ref = RobotModel.load()
    qd = np.zeros_like(q)
    for _ in range(ticks):
        ref.update(q, qd)
        q, qd = arm(q, qd, ref.nonlinear_effects(), DT)
    return q, qd


def test_scene_arm_factory_is_picklable_and_builds_the_patient_arm(tmp_path):
    factory = SceneArmFactory("impacts", {"patient.stiffness_n_per_m": 400.0})
    again = pickle.loads(pickle.dumps(factory))
    assert again == factory
    arm, sim = again.build(RobotModel.load())
    assert isinstance(arm, SceneArm) and arm.t == 0.0
    assert arm.patient.stiffness == 400.0
    assert np.allclose(arm.plant.q, sim.q0)
    # A scene without a patient: the emulator's rigid arm.
    bare = tmp_path / "bare.toml"
    bare.write_text('[scene]\nname = "bare"\n')
    assert isinstance(SceneArmFactory(str(bare))(RobotModel.load()), RigidArm)


def test_scene_arm_moves_the_hip_towards_the_intent_and_is_deterministic():
    arm, sim = SceneArmFactory("impacts").build(RobotModel.load())
    intent = sim.patient.intent
    q0 = sim.q0.copy()
    q, _ = _push(arm, q0, 640)  # 0.8 s: the intent leaves the start at 0.4 s
    assert arm.t == pytest.approx(0.8)
    goal = intent.position(arm.t)
    hip = arm.hip
    moved = hip - sim.hip0
    assert np.linalg.norm(moved) > 0.05
    # Towards the intent (the hand lags it through the muscle spring), not elsewhere.
    assert np.linalg.norm(goal - hip) < np.linalg.norm(goal - sim.hip0)
    assert moved @ (goal - sim.hip0) > 0.9 * np.linalg.norm(moved) * np.linalg.norm(goal - sim.hip0)
    # The inputs are not kept or changed; the same steps give the same state.
    assert np.array_equal(q0, sim.q0)
    arm2, _ = SceneArmFactory("impacts").build(RobotModel.load())
    q2, _ = _push(arm2, sim.q0.copy(), 640)
    assert np.array_equal(q, q2)


def test_scene_arm_clock_starts_at_its_first_call():
    arm, sim = SceneArmFactory("impacts").build(RobotModel.load())
    q, qd = sim.q0.copy(), np.zeros(6)
    # Held still (before the session is enabled) nothing calls the dynamics: the patient waits.
    assert arm.t == 0.0
    arm(q, qd, np.zeros(6), DT)
    assert arm.t == pytest.approx(DT)
    assert arm.calls == 1


# ----- a short session ---------------------------------------------------------------------------
def _check_session(rep: dict) -> None:
    assert rep["mode"] == HARDWARE_MODE
    assert rep["ticks"] > 0 and rep["enabled_ticks"] > 0
    assert rep["reached_enabled"]
    assert any(tr[2] == "enabled" for tr in rep["session"]["transitions"])
    assert rep["torque_before_enable_nm"] == 0.0
    est = rep["estimates"]
    assert sum(est["sent"].values()) > 20
    assert sum(est["admitted"].values()) > 0
    # Said in full when it fails: a session that faulted (a stalled machine) never gets there.
    assert est["fused_valid_ever"], {
        "transitions": rep["session"]["transitions"],
        "reactions": rep["session"].get("reactions"),
        "truth": rep["truth"],
        "admitted": est["admitted"],
    }
    assert rep["truth"]["samples"] > 100
    assert rep["truth"]["min_margin_m"] is not None
    assert rep["control"]["tick_us"]["p99"] is not None


def test_run_session_through_the_control_process():
    rep = run_session("impacts", ORACLE, 1.5)
    _check_session(rep)
    # The patient pushed the emulated arm towards the head (0.22 m away at the start).
    assert rep["truth"]["min_margin_m"] < 0.1
    json.dumps(rep)  # JSON-ready


def test_cli_run_hardware_writes_the_report(tmp_path, capsys):
    path = tmp_path / "hw.json"
    args = ["run", "impacts", "--hardware", "--duration", "1.5", "--report", str(path)]
    for key, value in ORACLE.items():
        args += ["--set", f"{key}={json.dumps(value)}"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "through the hardware layer: control process + emulated drives" in out
    _check_session(json.loads(path.read_text()))


def test_cli_run_hardware_bad_input(capsys):
    assert main(["run", "impacts", "--hardware", "--sweep", "surface.speed_mps=1,2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hapticloud: error:") and len(err.strip().splitlines()) == 1
    assert main(["run", "no-such-scene", "--hardware"]) == 2


def test_a_fault_before_enable_is_reset_once_its_cause_clears():
    """A session that faults before enable (a stall at start-up, here a persistent drive fault)
    is reset by ``run --hardware`` as an operator would: refused while the drive still reports
    the fault, taken once it has cleared; the fault is named for the report."""
    import threading

    from hapticloud.hardware.control import ControlProcess
    from hapticloud.hardware.session.run import _FAULT, _READY, _StateWaiter

    cp = ControlProcess("impacts", fifo_priority=None)
    cp.start(timeout=60.0)
    try:
        snaps: list = []
        waiter = _StateWaiter(cp, snaps)
        waiter.wait((_READY,), 30.0)
        cp.inject_drive_fault(3, persistent=True)
        waiter.wait((_FAULT,), 5.0)
        clear = threading.Timer(0.4, cp.clear_drive_fault, (3,))
        clear.start()
        t0 = cp.robot_state().t
        faults = waiter.ready(10.0)
        clear.join()
        assert cp.robot_state().state_code == _READY
        # Not before the drive cleared: the first resets were refused.
        assert cp.robot_state().t - t0 >= 0.4
        assert len(faults) == 1 and faults[0].startswith("fault: watchdog drive_fault")
        assert snaps and all(s.state != "enabled" for s in snaps)
    finally:
        cp.stop(timeout=20.0)


def test_a_fault_before_enable_that_does_not_clear_is_an_error():
    from hapticloud.hardware.control import ControlProcess
    from hapticloud.hardware.session.run import _FAULT, _READY, _StateWaiter

    cp = ControlProcess("impacts", fifo_priority=None)
    cp.start(timeout=60.0)
    try:
        waiter = _StateWaiter(cp, [])
        waiter.wait((_READY,), 30.0)
        cp.inject_drive_fault(1, persistent=True)
        waiter.wait((_FAULT,), 5.0)
        with pytest.raises(
            RuntimeError,
            match=r"faulted before enable .* did not clear in 1 s \(fault: watchdog drive_fault",
        ):
            waiter.ready(1.0)
    finally:
        cp.stop(timeout=20.0)
