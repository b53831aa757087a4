"""The emulated drives on their own: NMT, the CiA 402 state machine on raw frames, torque gating
and clamping, the arm, the bus-timing model, fault injection and the live thread."""

from __future__ import annotations

import time

import can
import numpy as np
import pytest
from hapticloud.hardware.drives import codec
from hapticloud.hardware.drives import protocol as p
from hapticloud.hardware.drives.config import DriveBusConfig
from hapticloud.hardware.drives.emulator import DriveEmulator, EmulatorConfig
from hapticloud.hardware.drives.faults import CAN_ERR_BUSOFF, FaultInjector
from hapticloud.hardware.drives.link import DriveLink
from hapticloud.hardware.drives.protocol import (
    CW_ENABLE_OPERATION,
    CW_FAULT_RESET,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
    DriveState,
    DriveTarget,
    EmcyCode,
)
from hapticloud.hardware.drives.schedule import frame_duration_s
from test_drive_link import FD, MODEL, Rig

ENABLED = DriveState.OPERATION_ENABLED


def raw_cycle(rig: Rig, cw: int, torque: float, limit: float = 80.0) -> None:
    """Send a command frame and SYNC straight onto the bus (bypassing the link's own gating)."""
    cycle = getattr(rig, "raw_counter", 0) + 1
    rig.raw_counter = cycle
    data = codec.encode_command(cycle, (cw,) * 6, (torque,) * 6, (limit,) * 6)
    rig.master_bus.send(can.Message(arbitration_id=p.COMMAND_ID, data=data, is_fd=True))
    sync = codec.encode_sync(cycle)
    rig.master_bus.send(can.Message(arbitration_id=p.SYNC_ID, data=sync, is_fd=True))
    rig.pump()


def states(rig: Rig) -> set[DriveState]:
    return set(rig.emu.state().state)


# ----- NMT ----------------------------------------------------------------------------------------
def test_drives_boot_preoperational_and_answer_only_after_nmt_start() -> None:
    with Rig(start=False, sniff=True) as rig:
        rig.pump()
        boot = rig.sniffed()
        assert sorted(m.arbitration_id for m in boot) == [
            p.HEARTBEAT_BASE_ID + n for n in range(1, 7)
        ]
        assert all(m.data == b"\x00" for m in boot)  # boot-up
        rig.cycle()
        rig.cycle()
        assert rig.link.poll_feedback().missing == tuple(range(6))
        assert rig.emu.state().syncs == 2  # seen, but PDOs are ignored in PRE-OPERATIONAL
        rig.link.start_nodes()
        rig.cycle()
        assert rig.link.poll_feedback().complete
        rig.link.send_nmt(p.NmtCommand.STOP, drive=2)
        rig.cycle()
        assert rig.link.poll_feedback().missing == (2,)
        assert rig.emu.state().nmt[2] is p.NmtState.STOPPED


# ----- CiA 402 on the drive side ------------------------------------------------------------------
def test_torque_flows_only_after_the_right_controlword_sequence() -> None:
    with Rig() as rig:
        for cw in (CW_ENABLE_OPERATION, CW_SWITCH_ON, CW_ENABLE_OPERATION):
            raw_cycle(rig, cw, 3.0)
            assert states(rig) == {DriveState.SWITCH_ON_DISABLED}
            assert not rig.emu.state().tau_nm.any()
        raw_cycle(rig, CW_SHUTDOWN, 3.0)
        assert states(rig) == {DriveState.READY_TO_SWITCH_ON}
        raw_cycle(rig, CW_SWITCH_ON, 3.0)
        assert states(rig) == {DriveState.SWITCHED_ON} and not rig.emu.state().tau_nm.any()
        raw_cycle(rig, CW_ENABLE_OPERATION, 3.0)
        assert states(rig) == {ENABLED}
        np.testing.assert_allclose(rig.emu.state().tau_nm, 3.0)
        raw_cycle(rig, CW_SWITCH_ON, 3.0)  # disable operation
        assert states(rig) == {DriveState.SWITCHED_ON} and not rig.emu.state().tau_nm.any()


def test_drive_clamps_to_the_command_limit_and_its_own() -> None:
    with Rig() as rig:
        for cw in (CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION):
            raw_cycle(rig, cw, 0.0)
        raw_cycle(rig, CW_ENABLE_OPERATION, 100.0, limit=10.0)
        np.testing.assert_allclose(rig.emu.state().tau_nm, 10.0)
        raw_cycle(rig, CW_ENABLE_OPERATION, -150.0, limit=160.0)
        np.testing.assert_allclose(rig.emu.state().tau_nm, -rig.cfg.tau_max)


def test_a_fault_removes_torque_until_reset_and_reenable() -> None:
    with Rig(sniff=True) as rig:
        for cw in (CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION, CW_ENABLE_OPERATION):
            raw_cycle(rig, cw, 4.0)
        rig.sniffed()
        t_inject = rig.clock()
        rig.faults.inject_drive_fault(5, EmcyCode.ENCODER)
        raw_cycle(rig, CW_ENABLE_OPERATION, 4.0)
        st = rig.emu.state()
        assert st.state[5] is DriveState.FAULT_REACTION_ACTIVE and st.tau_nm[5] == 0.0
        assert np.all(st.tau_nm[:5] == 4.0)
        fault_ev = next(e for e in rig.emu.events() if e.kind == "fault")
        assert (fault_ev.drive, fault_ev.detail) == (5, "0x7305")
        assert 0.0 <= fault_ev.t - t_inject <= rig.period
        emcy = [m for m in rig.sniffed() if m.arbitration_id == p.EMCY_BASE_ID + 6]
        assert codec.decode_emcy(emcy[0].data).code == EmcyCode.ENCODER
        for _ in range(10):  # enable keeps coming: no torque, stays in FAULT
            raw_cycle(rig, CW_ENABLE_OPERATION, 4.0)
            assert rig.emu.state().tau_nm[5] == 0.0
        assert rig.emu.state().state[5] is DriveState.FAULT
        raw_cycle(rig, CW_FAULT_RESET, 4.0)  # rising edge
        assert rig.emu.state().state[5] is DriveState.SWITCH_ON_DISABLED
        # The reset edge disables the healthy drives too (their controlword said so).
        for cw in (CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION):
            raw_cycle(rig, cw, 4.0)
        np.testing.assert_allclose(rig.emu.state().tau_nm, 4.0)
        codes = [codec.decode_emcy(m.data).code for m in rig.sniffed() if m.arbitration_id == 0x86]
        assert codes == [EmcyCode.NO_ERROR]


def test_quick_stop_brakes_the_arm() -> None:
    with Rig(emulator=EmulatorConfig(quick_stop_damping_nms=2.0)) as rig:
        rig.enable()
        qd0 = np.array([0.0, 0.0, 1.0, -1.0, 2.0, -2.0])
        rig.emu.set_arm_state(rig.emu.state().q, qd0)
        rig.link.run_sequence(DriveTarget.QUICK_STOP, pump=rig.pump)
        st = rig.emu.state()
        assert set(st.state) == {DriveState.QUICK_STOP_ACTIVE}
        # The braking torque opposes the motion.
        assert np.all(st.tau_nm * st.qd <= 0.0)
        speed0 = np.abs(st.qd[2:]).sum()
        for _ in range(40):
            rig.cycle(target=DriveTarget.QUICK_STOP)
        assert np.abs(rig.emu.state().qd[2:]).sum() < 0.5 * speed0


def test_command_timeout_faults_an_enabled_drive_and_reports_it() -> None:
    with Rig() as rig:
        rig.enable()
        rig.cycle()
        t_last = rig.clock() - rig.period  # the last command went out one pump ago
        for _ in range(10):  # SYNC only, no command frame
            rig.link.send_sync()
            rig.pump()
        timeouts = [e for e in rig.emu.events() if e.kind == "command_timeout"]
        assert len(timeouts) == 6
        limit = rig.emu.emulator_config.command_timeout_s
        assert all(limit < e.t - t_last <= limit + rig.period + 1e-9 for e in timeouts)
        fb = rig.link.poll_feedback()
        assert fb.faulted.all() and np.all(fb.error_code == EmcyCode.COMMAND_TIMEOUT)
        assert fb.command_missed.all()


# ----- the arm ------------------------------------------------------------------------------------
def test_brake_holds_a_disabled_arm_and_gravity_moves_a_free_one() -> None:
    with Rig() as rig:
        q0 = rig.emu.state().q
        for _ in range(20):
            rig.cycle(target=DriveTarget.DISABLED)
        np.testing.assert_array_equal(rig.emu.state().q, q0)
    with Rig(emulator=EmulatorConfig(brake_when_disabled=False)) as rig:
        q0 = rig.emu.state().q
        for _ in range(20):
            rig.cycle(target=DriveTarget.DISABLED)
        assert np.abs(rig.emu.state().q - q0).max() > 1e-3  # unpowered, the arm sags
        assert np.all(rig.emu.state().q >= MODEL.q_min) and np.all(rig.emu.state().q <= MODEL.q_max)


def test_pluggable_dynamics_gets_applied_torques_on_a_fixed_grid() -> None:
    calls: list[tuple[np.ndarray, float]] = []

    def integrator(q, qd, tau, dt):
        calls.append((tau.copy(), dt))
        return q + dt * 0.1, qd  # a constant 0.1 rad/s drift, whatever the torque

    cfg = EmulatorConfig(physics_substeps=2)
    with Rig(emulator=cfg, dynamics=integrator) as rig:
        rig.enable()
        calls.clear()
        q_before = rig.emu.state().q
        for _ in range(10):
            rig.cycle(np.full(6, 1.5))
        assert len(calls) == 20 and {dt for _, dt in calls} == {rig.period / 2}
        assert np.allclose(calls[-1][0], 1.5)
        np.testing.assert_allclose(rig.emu.state().q - q_before, 20 * rig.period / 2 * 0.1)
        fb = rig.link.poll_feedback()
        np.testing.assert_allclose(fb.position_rad, rig.emu.state().q, atol=1e-3)


# ----- bus timing ---------------------------------------------------------------------------------
def test_answers_are_released_at_their_modelled_wire_time() -> None:
    with Rig(sniff=True) as rig:
        rig.enable()
        cfg = rig.cfg
        rig.sniffed()
        t0 = rig.clock()
        rig.link.send_command(np.zeros(6), rig.link.controlwords(DriveTarget.ENABLED))
        rig.link.send_sync()
        rig.emu.step()
        assert [m for m in rig.sniffed() if m.arbitration_id > p.FEEDBACK_BASE_ID] == []
        assert rig.link.poll_feedback().missing == tuple(range(6))  # not on the wire yet
        rig.clock.advance(cfg.cycle_period_s)
        rig.emu.step()
        fbs = [m for m in rig.sniffed() if p.FEEDBACK_BASE_ID < m.arbitration_id < 0x190]
        assert [m.arbitration_id for m in fbs] == [p.FEEDBACK_BASE_ID + n for n in range(1, 7)]

        def dur(n: int) -> float:
            return frame_duration_s(n, cfg.nominal_bitrate, cfg.data_bitrate)

        sync_end = t0 + dur(p.COMMAND_DLC) + dur(p.SYNC_DLC)
        ready = sync_end + rig.emu.emulator_config.drive_response_s
        expected = [ready + (k + 1) * dur(p.FEEDBACK_DLC) for k in range(6)]
        np.testing.assert_allclose([m.timestamp for m in fbs], expected, rtol=0, atol=1e-9)
        assert expected[-1] - t0 < 0.6e-3  # the whole exchange fits in half a cycle
        assert rig.link.poll_feedback().complete


def test_without_bus_timing_answers_are_immediate() -> None:
    with Rig(emulator=EmulatorConfig(model_bus_timing=False, drive_response_s=0.0)) as rig:
        rig.link.send_command(np.zeros(6), (0,) * 6)
        rig.link.send_sync()
        rig.emu.step()
        assert rig.link.poll_feedback().complete


def test_added_latency_delays_answers_into_the_next_cycle() -> None:
    with Rig(sniff=True) as rig:
        rig.enable()
        rig.faults.set_latency(2 * rig.period)
        rig.sniffed()
        fbs = []
        for _ in range(6):
            fb, _ = rig.cycle()
            fbs.append(fb)
        assert all(not fb.complete for fb in fbs[1:])
        c = rig.link.counters
        assert c.feedback_late > 0 and c.feedback_missing > 0
        # The drives still see commands on time: torque and state are unaffected.
        assert set(rig.emu.state().state) == {ENABLED}


def test_heartbeats_at_the_producer_period_staggered() -> None:
    cfg = DriveBusConfig(heartbeat_period_s=0.005, heartbeat_timeout_s=0.012)
    with Rig(config=cfg, sniff=True) as rig:
        rig.sniffed()
        for _ in range(40):
            rig.pump()
        hbs = [m for m in rig.sniffed() if m.arbitration_id >= p.HEARTBEAT_BASE_ID]
        for node in range(1, 7):
            stamps = [m.timestamp for m in hbs if m.arbitration_id == p.HEARTBEAT_BASE_ID + node]
            assert len(stamps) >= 8
            np.testing.assert_allclose(np.diff(stamps), 0.005, atol=2e-4)
        assert all(m.data == bytes([p.NmtState.OPERATIONAL]) for m in hbs)
        first = sorted(m.timestamp for m in hbs[:6])
        assert np.diff(first).min() > 0.5e-3  # not one burst


# ----- fault injection plumbing -------------------------------------------------------------------
def test_injected_bus_reports_bus_off_like_socketcan() -> None:
    faults = FaultInjector()
    inner = can.Bus(interface="virtual", channel="drive-test-busoff", protocol=FD)
    other = can.Bus(interface="virtual", channel="drive-test-busoff", protocol=FD)
    bus = faults.wrap(inner)
    try:
        assert bus.protocol is FD and bus.state is can.BusState.ACTIVE
        faults.set_bus_off()
        err = bus.recv(0.0)
        assert err is not None and err.is_error_frame and err.arbitration_id & CAN_ERR_BUSOFF
        assert bus.recv(0.0) is None  # reported once
        with pytest.raises(can.CanOperationError, match="bus-off"):
            bus.send(can.Message(arbitration_id=1, data=b"", is_fd=True))
        other.send(can.Message(arbitration_id=2, data=b"", is_fd=True))
        assert bus.recv(0.0) is None  # nothing gets through while off
        assert bus.state is can.BusState.ERROR
        faults.set_bus_off(False)
        bus.send(can.Message(arbitration_id=1, data=b"", is_fd=True))
        assert other.recv(0.0).arbitration_id == 1
    finally:
        bus.shutdown()
        other.shutdown()


def test_fault_injector_validates_its_arguments() -> None:
    from hapticloud.core.errors import InputError

    faults = FaultInjector()
    with pytest.raises(InputError, match="drive"):
        faults.inject_drive_fault(6)
    with pytest.raises(InputError, match="code"):
        faults.inject_drive_fault(0, 0)
    with pytest.raises(InputError, match="loss rate"):
        faults.set_loss(tx=1.5)
    with pytest.raises(InputError, match="latency"):
        faults.set_latency(-1.0)


# ----- live ---------------------------------------------------------------------------------------
def test_live_thread_answers_a_real_time_link() -> None:
    """The emulator on its own thread against time.monotonic. Only liveness is asserted (the
    sequence has a generous timeout); timing is asserted in the stepped tests above."""
    channel = "drive-test-live"
    master = can.Bus(interface="virtual", channel=channel, protocol=FD)
    drives = can.Bus(interface="virtual", channel=channel, protocol=FD)
    emu = DriveEmulator(drives, model=MODEL)
    try:
        emu.start()
        link = DriveLink(master)
        link.start_nodes()
        fb = link.run_sequence(DriveTarget.ENABLED, timeout_s=5.0)
        assert fb.all_enabled
        deadline = time.monotonic() + 2.0
        while not (fb := link.poll_feedback(deadline=deadline)).complete:
            link.send_command(np.zeros(6), link.controlwords(DriveTarget.ENABLED))
            link.send_sync()
        assert fb.complete and np.isfinite(fb.heartbeat_age_s).all()
    finally:
        emu.stop()
        master.shutdown()
        drives.shutdown()
    assert emu._thread is None
