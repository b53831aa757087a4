"""The master side of the drive bus against the emulated drives, on python-can's ``virtual``
interface, stepped by a fake clock: every timing below is read from recorded stamps, no test
sleeps."""

from __future__ import annotations

import itertools
import math
import sys

import can
import numpy as np
import pytest
from hapticloud.core.errors import ConfigError, DriveError, InputError
from hapticloud.core.robot import RobotModel
from hapticloud.hardware.drives import codec, schedule
from hapticloud.hardware.drives import protocol as p
from hapticloud.hardware.drives.config import DriveBusConfig
from hapticloud.hardware.drives.emulator import DriveEmulator, EmulatorConfig
from hapticloud.hardware.drives.faults import FaultConfig, FaultInjector
from hapticloud.hardware.drives.link import DriveFeedback, DriveLink
from hapticloud.hardware.drives.protocol import DriveState, DriveTarget, EmcyCode
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

FD = can.CanProtocol.CAN_FD
MODEL = RobotModel.load()
_channels = itertools.count()


class FakeClock:
    """A clock the test moves by hand (s)."""

    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt


class Rig:
    """DriveLink + DriveEmulator on one virtual channel, stepped by one fake clock.

    ``sniffer`` (optional) is a third bus on the channel that records every frame both sides
    send, as a bus analyser would.
    """

    def __init__(
        self,
        *,
        config: DriveBusConfig | None = None,
        emulator: EmulatorConfig | None = None,
        faults: FaultInjector | None = None,
        wrap: bool = False,
        start: bool = True,
        sniff: bool = False,
        dynamics=None,
    ) -> None:
        channel = f"drive-test-{next(_channels)}"
        self.clock = FakeClock()
        self.cfg = config or DriveBusConfig()
        self.faults = faults or FaultInjector()
        master = can.Bus(interface="virtual", channel=channel, protocol=FD)
        self.master_bus = self.faults.wrap(master) if wrap else master
        self.drive_bus = can.Bus(
            interface="virtual", channel=channel, protocol=FD, preserve_timestamps=True
        )
        self.sniffer = can.Bus(interface="virtual", channel=channel, protocol=FD) if sniff else None
        self.link = DriveLink(self.master_bus, self.cfg, clock=self.clock)
        self.emu = DriveEmulator(
            self.drive_bus,
            self.cfg,
            emulator,
            model=MODEL,
            dynamics=dynamics,
            faults=self.faults,
            clock=self.clock,
        )
        self.emu.step()
        if start:
            self.link.start_nodes()
            self.pump()

    @property
    def period(self) -> float:
        return self.cfg.cycle_period_s

    def pump(self) -> None:
        """The drives' side of one cycle: take what was sent now, let a period pass."""
        self.emu.step()
        self.clock.advance(self.period)
        self.emu.step()

    def cycle(
        self,
        torques=None,
        target: DriveTarget | tuple[DriveTarget, ...] = DriveTarget.ENABLED,
        controlwords=None,
    ) -> tuple[DriveFeedback, np.ndarray]:
        """One control tick: read feedback, send command + SYNC, let the drives answer."""
        fb = self.link.poll_feedback()
        cws = controlwords if controlwords is not None else self.link.controlwords(target)
        sent = self.link.send_command(np.zeros(6) if torques is None else torques, cws)
        self.link.send_sync()
        self.pump()
        return fb, sent

    def enable(self) -> DriveFeedback:
        return self.link.run_sequence(DriveTarget.ENABLED, pump=self.pump)

    def sniffed(self, can_id: int | None = None) -> list[can.Message]:
        assert self.sniffer is not None
        out = []
        while (msg := self.sniffer.recv(0.0)) is not None:
            if can_id is None or msg.arbitration_id == can_id:
                out.append(msg)
        return out

    def close(self) -> None:
        for bus in (self.master_bus, self.drive_bus, self.sniffer):
            if bus is not None:
                bus.shutdown()

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _commands(msgs: list[can.Message]) -> list[codec.CommandFrame]:
    return [codec.decode_command(m.data) for m in msgs if m.arbitration_id == p.COMMAND_ID]


# ----- construction and the happy path ------------------------------------------------------------
def test_link_refuses_a_classic_can_bus() -> None:
    bus = can.Bus(interface="virtual", channel="drive-test-classic")
    try:
        with pytest.raises(ConfigError, match="CAN FD"):
            DriveLink(bus)
    finally:
        bus.shutdown()


def test_enable_sequence_reaches_operation_enabled_and_snapshots_are_immutable() -> None:
    with Rig() as rig:
        fb0 = rig.link.poll_feedback()
        assert fb0.nmt_state == (p.NmtState.BOOT_UP,) * 6  # heartbeats come every 10 ms
        for _ in range(int(rig.cfg.heartbeat_period_s / rig.period) + 1):
            rig.pump()
        fb0 = rig.link.poll_feedback()
        assert fb0.nmt_state == (p.NmtState.OPERATIONAL,) * 6
        assert not fb0.all_enabled
        fb = rig.enable()
        assert fb.all_enabled and fb.complete and not fb.any_fault and fb.seq > fb0.seq
        with pytest.raises(ValueError, match="read-only"):
            fb.position_rad[0] = 1.0
        # Positions are the emulated arm's, to the LSB.
        np.testing.assert_allclose(fb.position_rad, MODEL.q_home, atol=p.POSITION_LSB_RAD)
        kinds = [(e.drive, e.detail) for e in rig.link.pop_events() if e.kind == "state"]
        assert kinds[-6:] == [(i, "OPERATION_ENABLED") for i in range(6)]
        # The observed load matches the planned one (heartbeats included; worst-case stuffing).
        for _ in range(8):
            rig.cycle()
        early = rig.link.poll_feedback()
        for _ in range(80):
            rig.cycle()
        late = rig.link.poll_feedback()
        planned = schedule.config_load(rig.cfg).load
        assert late.bus_load_since(early) == pytest.approx(planned, rel=0.02)
        # Disable: back to READY TO SWITCH ON.
        fb = rig.link.run_sequence(DriveTarget.DISABLED, pump=rig.pump)
        assert fb.state == (DriveState.READY_TO_SWITCH_ON,) * 6


def test_torque_is_zero_before_enable_and_clamped_after() -> None:
    with Rig(sniff=True) as rig:
        big = np.array([10.0, -10.0, 10.0, -10.0, 10.0, -10.0])
        for _ in range(3):
            _, sent = rig.cycle(big, DriveTarget.DISABLED)
            assert not sent.any()
        assert all(not any(c.torque_nm) for c in _commands(rig.sniffed()))
        assert rig.link.counters.torques_blocked >= 18
        rig.enable()
        rig.sniffed()
        huge = np.array([1e3, -1e3, 55.5, -1e9, math.nan, math.inf])
        rig.cycle(huge)
        _, sent = rig.cycle(huge)
        cmd = _commands(rig.sniffed())[-1]
        tau_max = rig.cfg.tau_max
        np.testing.assert_allclose(sent, [80.0, -80.0, 55.5, -80.0, 0.0, 0.0])
        np.testing.assert_allclose(cmd.torque_nm, sent)
        np.testing.assert_allclose(cmd.torque_limit_nm, tau_max)
        c = rig.link.counters
        assert c.torques_nonfinite == 4 and c.torques_clamped == 6
        # The drives apply what was sent.
        np.testing.assert_allclose(rig.emu.state().tau_nm, sent)


def test_torques_beyond_any_float_range_saturate_and_never_raise() -> None:
    """Above ~9e305 N m a torque's count overflows a float (round(inf) raised OverflowError on
    the hot path): such torques are clamped to the limit like any other too large one; NaN and
    +-inf are 0 (non-finite, as documented); nothing raises."""
    with Rig(sniff=True) as rig:
        rig.enable()
        rig.sniffed()
        counters = rig.link.counters
        huge = np.array([1e308, -1e308, sys.float_info.max, 1e306, -9e305, math.nan])
        _, sent = rig.cycle(huge)
        np.testing.assert_allclose(sent, [80.0, -80.0, 80.0, 80.0, -40.0, 0.0])
        _, sent = rig.cycle(
            np.array([math.inf, -math.inf, math.nan, -sys.float_info.max, 5e-324, -0.0])
        )
        np.testing.assert_allclose(sent, [0.0, 0.0, 0.0, -80.0, 0.0, 0.0])
        cmds = _commands(rig.sniffed())
        np.testing.assert_allclose(cmds[-2].torque_nm, [80.0, -80.0, 80.0, 80.0, -40.0, 0.0])
        np.testing.assert_allclose(cmds[-1].torque_nm, [0.0, 0.0, 0.0, -80.0, 0.0, 0.0])
        c = rig.link.counters
        assert c.torques_clamped - counters.torques_clamped == 6
        assert c.torques_nonfinite - counters.torques_nonfinite == 4
        # The same through send_cycle (command and SYNC in one burst).
        sent = rig.link.send_cycle(huge, rig.link.controlwords(DriveTarget.ENABLED))
        np.testing.assert_allclose(sent, [80.0, -80.0, 80.0, 80.0, -40.0, 0.0])
        # A NaN limit is refused where limits are set (a limit of 0 is the safe one).
        with pytest.raises(InputError, match="limits_nm"):
            rig.link.set_torque_limits([math.nan] * 6)
        rig.link.set_torque_limits(math.inf)  # cut to the configured limits
        np.testing.assert_allclose(rig.link.torque_limits, rig.cfg.tau_max)


def test_run_time_torque_limits_only_go_down() -> None:
    with Rig(sniff=True) as rig:
        rig.enable()
        rig.link.set_torque_limits([5.0, 200.0, 5.0, 5.0, 5.0, 5.0])
        np.testing.assert_allclose(rig.link.torque_limits, [5.0, 80.0, 5.0, 5.0, 5.0, 5.0])
        _, sent = rig.cycle(np.full(6, 60.0))
        np.testing.assert_allclose(sent, [5.0, 60.0, 5.0, 5.0, 5.0, 5.0])
        cmd = _commands(rig.sniffed())[-1]
        np.testing.assert_allclose(cmd.torque_limit_nm, rig.link.torque_limits)
        with pytest.raises(InputError, match="limits_nm"):
            rig.link.set_torque_limits([-1.0] * 6)
        with pytest.raises(InputError, match="torques"):
            rig.link.send_command(np.zeros(5), (0,) * 6)
        with pytest.raises(InputError, match="16-bit"):
            rig.link.send_command(np.zeros(6), (0x10000,) * 6)


_TARGETS = st.sampled_from([DriveTarget.ENABLED] * 4 + list(DriveTarget))


@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(
    steps=st.lists(
        st.tuples(
            st.lists(
                st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=6, max_size=6
            ),
            _TARGETS,
            st.integers(1, 6),
            st.one_of(st.none(), st.integers(0, 5)),
            st.one_of(st.none(), st.integers(0, 5)),
        ),
        min_size=3,
        max_size=15,
    )
)
def test_property_torques_never_exceed_limits_and_are_zero_unless_enabled(steps) -> None:
    """Any torques (huge, NaN, inf), any targets, drives faulting or going silent at any time:
    no frame carries a torque above a drive's limit, and none is non-zero for a drive whose
    latest fresh feedback was not OPERATION ENABLED."""
    with Rig(sniff=True) as rig:
        tau_max = rig.cfg.tau_max
        for torques, target, repeats, fault, silent in steps:
            if fault is not None:
                rig.faults.inject_drive_fault(fault, EmcyCode.OVERVOLTAGE)
            rig.faults.set_silent(None, False)
            if silent is not None:
                rig.faults.set_silent(silent)
            for _ in range(repeats):
                before = rig.link.poll_feedback()
                enabled = before.enabled.copy()
                cws = rig.link.controlwords(target)
                sent = rig.link.send_command(np.array(torques, dtype=np.float64), cws)
                rig.link.send_sync()
                rig.pump()
                assert np.all(np.abs(sent) <= tau_max)
                for i in range(6):
                    if sent[i] != 0.0:
                        assert enabled[i] and (cws[i] & 0x8F) == p.CW_ENABLE_OPERATION
                # What the drives apply obeys the same limits.
                assert np.all(np.abs(rig.emu.state().tau_nm) <= tau_max + 1e-12)
        for cmd in _commands(rig.sniffed()):
            assert np.all(np.abs(cmd.torque_nm) <= tau_max)


# ----- faults the link must see -------------------------------------------------------------------
def test_link_sees_a_drive_fault_bit_and_its_emcy_and_resets_it() -> None:
    with Rig(sniff=True) as rig:
        rig.enable()
        tau = np.full(6, 2.0)
        for _ in range(5):
            rig.cycle(tau)
        t_fault = rig.clock()
        rig.faults.inject_drive_fault(2, EmcyCode.OVERCURRENT)
        rig.cycle(tau)  # the drive faults at this SYNC
        fb, sent = rig.cycle(tau)
        assert fb.faulted[2] and fb.any_fault and not fb.faulted[[0, 1, 3, 4, 5]].any()
        assert fb.state[2] in (DriveState.FAULT_REACTION_ACTIVE, DriveState.FAULT)
        assert fb.error_code[2] == EmcyCode.OVERCURRENT
        assert sent[2] == 0.0 and np.all(sent[[0, 1, 3, 4, 5]] == 2.0)
        (emcy,) = rig.link.pop_emergencies()
        assert (emcy.drive, emcy.code) == (2, EmcyCode.OVERCURRENT)
        assert emcy.register & p.ErrorRegister.CURRENT
        # Seen within two cycles of the injection (the fault acts at the next SYNC).
        assert emcy.stamp - t_fault <= 2 * rig.period + 1e-9
        assert rig.emu.state().tau_nm[2] == 0.0
        # Enabling does not reset a fault; FAULT_RESET does, with an EMCY "no error".
        for _ in range(6):
            fb, sent = rig.cycle(tau)
        assert fb.state[2] is DriveState.FAULT and sent[2] == 0.0
        fb = rig.link.run_sequence(DriveTarget.FAULT_RESET, pump=rig.pump)
        assert fb.state[2] is DriveState.SWITCH_ON_DISABLED
        rig.link.poll_feedback()
        assert [e.code for e in rig.link.pop_emergencies()] == [EmcyCode.NO_ERROR]
        assert rig.link.snapshot().error_code[2] == 0
        assert rig.enable().all_enabled


def test_persistent_fault_makes_the_enable_sequence_fail_with_drive_error() -> None:
    with Rig() as rig:
        rig.faults.inject_drive_fault(1, EmcyCode.OVERTEMPERATURE, persistent=True)
        with pytest.raises(DriveError, match=r"enabled within 0.05 s \(1: FAULT"):
            rig.link.run_sequence(DriveTarget.ENABLED, timeout_s=0.05, pump=rig.pump)
        with pytest.raises(DriveError, match="1: FAULT"):
            rig.link.run_sequence(DriveTarget.FAULT_RESET, timeout_s=0.02, pump=rig.pump)
        rig.faults.clear_drive_fault(1)
        rig.link.run_sequence(DriveTarget.FAULT_RESET, pump=rig.pump)
        assert rig.enable().all_enabled


def test_heartbeat_loss_is_detected_after_the_timeout() -> None:
    with Rig() as rig:
        rig.enable()
        timeout = rig.cfg.heartbeat_timeout_s
        rig.faults.set_heartbeat_loss(3)
        fb = rig.link.poll_feedback()
        last_seen = fb.stamp - fb.heartbeat_age_s[3]
        detected = None
        for _ in range(100):
            fb, _ = rig.cycle()
            assert not fb.heartbeat_lost[[0, 1, 2, 4, 5]].any()
            if fb.heartbeat_lost[3]:
                detected = fb
                break
        assert detected is not None
        # Flagged at the first poll after the timeout ran out, from the recorded stamps.
        assert detected.stamp - last_seen > timeout
        assert detected.stamp - last_seen <= timeout + rig.period + 1e-9
        # The feedback kept flowing: only the heartbeat was missing.
        assert detected.age_s[3] <= rig.period + 1e-9
        ev = [e for e in rig.link.pop_events() if e.kind.startswith("heartbeat")]
        assert [(e.drive, e.kind, e.stamp) for e in ev] == [(3, "heartbeat_lost", detected.stamp)]
        rig.faults.set_heartbeat_loss(3, lost=False)
        for _ in range(int(rig.cfg.heartbeat_period_s / rig.period) + 2):
            fb, _ = rig.cycle()
        assert not fb.heartbeat_lost.any()
        assert [e.kind for e in rig.link.pop_events() if e.drive == 3] == ["heartbeat_back"]


def test_heartbeat_never_seen_counts_from_link_start() -> None:
    with Rig(start=False) as rig:
        rig.faults.set_heartbeat_loss()
        rig.clock.advance(rig.cfg.heartbeat_timeout_s * 0.9)
        assert not rig.link.poll_feedback().heartbeat_lost.any()
        rig.clock.advance(rig.cfg.heartbeat_timeout_s * 0.2)
        fb = rig.link.poll_feedback()
        assert fb.heartbeat_lost.all() and np.isinf(fb.heartbeat_age_s).all()


@pytest.mark.parametrize("rate", [0.01, 0.10])
def test_lost_feedback_frames_are_counted(rate: float) -> None:
    cycles = 2000
    faults = FaultInjector(FaultConfig(tx_loss_rate=rate, seed=11))
    with Rig(faults=faults) as rig:
        for _ in range(cycles):
            rig.cycle(target=DriveTarget.DISABLED)
        fb = rig.link.poll_feedback()
        missing = fb.counters.feedback_missing + len(fb.missing)
        dropped = rig.faults.counters.dropped["feedback"]
        assert missing == dropped
        assert fb.counters.feedback_late == 0
        n = 6 * cycles
        assert abs(dropped - rate * n) < 5 * math.sqrt(n * rate * (1 - rate))
        assert fb.counters.feedback_received == n - dropped


@pytest.mark.parametrize("rate", [0.01, 0.10])
def test_lost_commands_and_syncs_are_counted(rate: float) -> None:
    cycles = 2000
    faults = FaultInjector(FaultConfig(rx_loss_rate=rate, seed=5))
    with Rig(faults=faults) as rig:
        for _ in range(cycles):
            rig.cycle(target=DriveTarget.DISABLED)
        fb = rig.link.poll_feedback()
        dropped = rig.faults.counters.dropped
        # A lost SYNC silences all six drives for that cycle.
        assert fb.counters.feedback_missing + len(fb.missing) == 6 * dropped["sync"]
        # A lost command is reported by every drive that got the SYNC: it held the last one.
        assert fb.counters.commands_missed == sum(rig.emu.state().commands_missed)
        assert 6 * dropped["command"] >= fb.counters.commands_missed > 0
        for kind in ("sync", "command"):
            mean, sd = rate * cycles, math.sqrt(cycles * rate * (1 - rate))
            assert abs(dropped[kind] - mean) < 5 * sd


def test_bus_off_is_reported_and_the_drives_drop_torque() -> None:
    with Rig(wrap=True) as rig:
        rig.enable()
        for _ in range(3):
            rig.cycle(np.full(6, 1.0))
        t_off = rig.clock()
        rig.faults.set_bus_off()
        fb, _ = rig.cycle(np.full(6, 1.0))
        assert fb.bus_off  # the error frame arrived
        assert rig.link.bus.state is can.BusState.ERROR
        (ev,) = [e for e in rig.link.pop_events() if e.kind == "bus_off"]
        assert ev.stamp == t_off
        for _ in range(8):
            fb, _ = rig.cycle(np.full(6, 1.0))
        assert fb.bus_off and fb.counters.send_errors >= 16 and fb.counters.bus_off_events == 1
        # Cut off from their master the drives fault on their command timeout: torque off.
        timeouts = [e for e in rig.emu.events() if e.kind == "command_timeout"]
        assert len(timeouts) == 6
        limit = rig.emu.emulator_config.command_timeout_s + rig.period
        assert all(0 < e.t - t_off <= limit + 1e-9 for e in timeouts)
        assert not rig.emu.state().tau_nm.any()
        rig.faults.set_bus_off(False)
        rig.cycle()
        fb, _ = rig.cycle()
        assert not fb.bus_off and fb.all_enabled is False and fb.faulted.all()
        assert [e.kind for e in rig.link.pop_events() if e.drive == -1] == ["bus_back"]


def test_bus_off_from_failed_sends_alone() -> None:
    """A backend that reports no error frames: consecutive failed sends count as bus-off."""
    cfg = DriveBusConfig(send_errors_for_bus_off=3)
    faults = FaultInjector()
    with Rig(config=cfg, faults=faults, wrap=True) as rig:
        rig.link.poll_feedback()
        faults.set_bus_off()
        rig.link.bus._reported = faults.bus_off_events  # swallow the error frame
        rig.link.send_command(np.zeros(6), (0,) * 6)
        rig.link.send_sync()
        assert not rig.link.snapshot().bus_off
        rig.link.send_command(np.zeros(6), (0,) * 6)
        assert rig.link.snapshot().bus_off


def test_a_silent_drive_goes_stale_and_gets_no_torque() -> None:
    with Rig() as rig:
        rig.enable()
        rig.faults.set_silent(4)
        stale_at = None
        for k in range(10):
            fb, sent = rig.cycle(np.full(6, 1.0))
            if k >= 1:
                assert fb.missing == (4,)
            if fb.stale[4] and stale_at is None:
                stale_at = fb
        assert stale_at is not None
        assert stale_at.age_s[4] > rig.cfg.feedback_timeout_s
        assert stale_at.age_s[4] <= rig.cfg.feedback_timeout_s + rig.period + 1e-9
        assert sent[4] == 0.0 and np.all(sent[[0, 1, 2, 3, 5]] == 1.0)
        assert not fb.enabled[4] and not fb.all_enabled


def test_poll_with_a_deadline_and_offline_decoding() -> None:
    with Rig(sniff=True) as rig:
        rig.enable()
        rig.link.send_command(np.zeros(6), rig.link.controlwords(DriveTarget.ENABLED))
        rig.link.send_sync()
        # Nothing has answered yet and the deadline is now: returns at once, incomplete.
        fb = rig.link.poll_feedback(deadline=rig.clock())
        assert fb.missing == tuple(range(6))
        rig.pump()
        fb = rig.link.poll_feedback(deadline=rig.clock() + 1.0)
        assert fb.complete
        # A recorded trace decodes through a second link (no bus traffic needed).
        log = rig.sniffed()
        spare = can.Bus(interface="virtual", channel="drive-test-offline", protocol=FD)
        try:
            offline = DriveLink(spare, clock=rig.clock)
            for msg in log:
                offline.handle(msg)
            snap = offline.snapshot()
            assert snap.state == (DriveState.OPERATION_ENABLED,) * 6
            np.testing.assert_allclose(snap.position_rad, fb.position_rad)
        finally:
            spare.shutdown()


@pytest.mark.parametrize("socketpair", [False, True])
def test_frames_read_ahead_give_the_same_feedback_as_one_poll(socketpair: bool) -> None:
    """The control loop decodes the drives' answers in its spin before the deadline
    (``read_pending``), then polls at the deadline: same snapshot as polling once."""
    from hapticloud.hardware.drives.bench import open_bus_pair

    def run(read_ahead: bool) -> list[DriveFeedback]:
        if socketpair:
            master, drives = open_bus_pair("socketpair")
        else:
            master, drives = open_bus_pair("virtual")
        clock = FakeClock()
        try:
            link = DriveLink(master, clock=clock)
            emu = DriveEmulator(
                drives, emulator=EmulatorConfig(model_bus_timing=False), model=MODEL, clock=clock
            )

            def pump() -> None:
                emu.step()
                clock.advance(link.config.cycle_period_s)
                emu.step()

            emu.step()
            link.start_nodes()
            pump()
            link.run_sequence(DriveTarget.ENABLED, pump=pump)
            out = []
            for k in range(20):
                link.send_cycle(np.full(6, 0.1 * k), link.controlwords(DriveTarget.ENABLED))
                pump()
                if read_ahead:
                    # The six answers (and any heartbeat) are in; nothing is left for the poll.
                    assert link.read_pending() >= 6
                    assert link.read_pending() == 0
                out.append(link.poll_feedback())
            return out
        finally:
            master.shutdown()
            drives.shutdown()

    once, ahead = run(False), run(True)
    for a, b in zip(once, ahead, strict=True):
        assert a.complete and b.complete
        np.testing.assert_array_equal(a.position_rad, b.position_rad)
        np.testing.assert_array_equal(a.velocity_rad_s, b.velocity_rad_s)
        np.testing.assert_array_equal(a.torque_nm, b.torque_nm)
        assert a.state == b.state and a.counters == b.counters


def test_a_dead_bus_never_raises_into_the_loop() -> None:
    bus = can.Bus(interface="virtual", channel="drive-test-dead", protocol=FD)
    link = DriveLink(bus, clock=FakeClock())
    bus.shutdown()  # python-can now raises CanOperationError from send and recv
    fb = link.poll_feedback()
    assert fb.counters.receive_errors == 1
    for _ in range(3):
        link.send_command(np.zeros(6), (0,) * 6)
    assert link.snapshot().bus_off and link.counters.send_errors == 3
