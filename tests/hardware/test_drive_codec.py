"""The drive protocol on paper: frame codecs against the DBC, scaling, the CiA 402 state machine
and the bus-load arithmetic."""

from __future__ import annotations

import doctest
import importlib
import math
import sys
from pathlib import Path

import cantools
import pytest
from hapticloud.core.errors import ConfigError
from hapticloud.hardware.drives import codec, schedule
from hapticloud.hardware.drives import protocol as p
from hapticloud.hardware.drives.config import DriveBusConfig
from hapticloud.hardware.drives.protocol import (
    CW_ENABLE_OPERATION,
    CW_FAULT_RESET,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
    DriveState,
    DriveTarget,
)
from hypothesis import given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[2]
DBC_PATH = ROOT / "assets" / "can" / "anyexo_drives.dbc"
LSB_T, LSB_Q, LSB_V = p.TORQUE_LSB_NM, p.POSITION_LSB_RAD, p.VELOCITY_LSB_RAD_S

words = st.integers(0, 0xFFFF)
torques = st.floats(-p.TORQUE_RANGE_NM, p.TORQUE_RANGE_NM)
limits = st.floats(0.0, 160.0)
six = st.lists


@pytest.fixture(scope="module")
def db() -> cantools.database.can.Database:
    return cantools.database.load_file(DBC_PATH)


# ----- codecs -------------------------------------------------------------------------------------
@given(
    cycle=st.integers(0, 2**32 - 1),
    cws=six(words, min_size=6, max_size=6),
    tau=six(torques, min_size=6, max_size=6),
    lim=six(limits, min_size=6, max_size=6),
)
def test_command_round_trip(cycle, cws, tau, lim) -> None:
    data = codec.encode_command(cycle, cws, tau, lim)
    assert len(data) == p.COMMAND_DLC and data[p.COMMAND_USED :] == bytes(8)
    frame = codec.decode_command(data)
    assert frame.cycle == cycle and list(frame.controlword) == cws
    for sent, got in zip(tau, frame.torque_nm, strict=True):
        assert abs(sent - got) <= LSB_T / 2 + 1e-12
    for sent, got in zip(lim, frame.torque_limit_nm, strict=True):
        # Limits round down: the drive never gets a larger limit than asked for.
        assert sent - LSB_T - 1e-9 <= got <= sent + 1e-9


@given(
    pos=st.floats(-2000.0, 2000.0),
    vel=st.floats(-p.VELOCITY_RANGE_RAD_S, p.VELOCITY_RANGE_RAD_S),
    tau=torques,
    sw=words,
    sync=st.integers(0, 255),
    cmd=st.integers(0, 255),
)
def test_feedback_round_trip(pos, vel, tau, sw, sync, cmd) -> None:
    data = codec.encode_feedback(pos, vel, tau, sw, sync, cmd)
    assert len(data) == p.FEEDBACK_DLC
    fb = codec.decode_feedback(data)
    assert abs(fb.position_rad - pos) <= LSB_Q / 2 + 1e-9
    assert abs(fb.velocity_rad_s - vel) <= LSB_V / 2 + 1e-12
    assert abs(fb.torque_nm - tau) <= LSB_T / 2 + 1e-12
    assert (fb.statusword, fb.sync_counter, fb.command_counter) == (sw, sync, cmd)


def test_small_frames_round_trip() -> None:
    e = codec.decode_emcy(codec.encode_emcy(0x2310, 0x03, 4, 123456))
    assert e == codec.Emergency(0x2310, 0x03, 4, 123456)
    assert codec.encode_sync(0x1FF) == b"\xff"
    assert codec.encode_heartbeat(p.NmtState.OPERATIONAL) == b"\x05"
    assert codec.encode_nmt(p.NmtCommand.START, 0) == b"\x01\x00"


def test_scaling_saturates_instead_of_wrapping() -> None:
    assert codec.torque_to_raw(1e6) == p.INT16_MAX
    assert codec.torque_to_raw(-1e6) == p.INT16_MIN
    assert codec.torque_to_raw(math.inf) == p.INT16_MAX
    assert codec.torque_to_raw(math.nan) == 0  # never a full-scale command from a NaN
    assert codec.velocity_to_raw(100.0) == p.INT16_MAX
    assert codec.velocity_to_raw(-100.0) == p.INT16_MIN
    assert codec.position_to_raw(1e5) == p.INT32_MAX
    assert codec.position_to_raw(-1e5) == p.INT32_MIN
    assert codec.torque_limit_to_raw(-3.0) == 0
    assert codec.torque_limit_to_raw(math.nan) == 0
    assert codec.torque_limit_to_raw(1e6) == p.UINT16_MAX
    fb = codec.decode_feedback(codec.encode_feedback(0.0, 1e3, -1e3, 0, 0, 0))
    assert fb.velocity_rad_s == pytest.approx(p.VELOCITY_RANGE_RAD_S)
    assert fb.torque_nm == pytest.approx(p.INT16_MIN * LSB_T)


_EXTREMES = (
    math.inf,
    -math.inf,
    math.nan,
    1e308,
    -1e308,
    sys.float_info.max,
    -sys.float_info.max,
    1e306,
    9e305,
    5e-324,
    -0.0,
)


def test_torque_limit_saturates_at_every_float() -> None:
    """A limit beyond the uint16 field (inf, 1e308: their count overflows a float) is the
    largest count; NaN and limits <= 0 are 0, the safe limit (the drive then clamps every
    target to zero torque). The configuration refuses such limits before they get here."""
    assert codec.torque_limit_to_raw(math.inf) == p.UINT16_MAX
    assert codec.torque_limit_to_raw(1e308) == p.UINT16_MAX
    assert codec.torque_limit_to_raw(sys.float_info.max) == p.UINT16_MAX
    assert codec.torque_limit_to_raw(-math.inf) == 0
    assert codec.torque_limit_to_raw(-1e308) == 0
    assert codec.torque_limit_to_raw(math.nan) == 0
    assert codec.torque_limit_to_raw(5e-324) == 0  # rounded down
    assert codec.torque_limit_to_raw(p.UINT16_MAX * LSB_T) == p.UINT16_MAX
    for bad in (math.inf, math.nan):
        with pytest.raises(ConfigError, match="finite"):
            DriveBusConfig(tau_max_nm=(bad,) * p.N_DRIVES)
    # The torque field too: saturated at its range, NaN is 0, never a full-scale command.
    expected = (p.INT16_MAX, p.INT16_MIN, 0, p.INT16_MAX, p.INT16_MIN, p.INT16_MAX)
    expected += (p.INT16_MIN, p.INT16_MAX, p.INT16_MAX, 0, 0)
    assert tuple(codec.torque_to_raw(v) for v in _EXTREMES) == expected
    frame = codec.decode_command(codec.encode_command(7, (0,) * 6, _EXTREMES[:6], _EXTREMES[:6]))
    assert frame.torque_nm == pytest.approx(
        [
            p.TORQUE_RANGE_NM,
            p.INT16_MIN * LSB_T,
            0.0,
            p.TORQUE_RANGE_NM,
            p.INT16_MIN * LSB_T,
            p.TORQUE_RANGE_NM,
        ]
    )
    assert frame.torque_limit_nm == pytest.approx(
        [p.UINT16_MAX * LSB_T, 0.0, 0.0, p.UINT16_MAX * LSB_T, 0.0, p.UINT16_MAX * LSB_T]
    )


@given(
    tau=six(st.floats(), min_size=6, max_size=6),
    lim=six(st.floats(), min_size=6, max_size=6),
)
def test_command_encoding_never_raises_on_any_float(tau, lim) -> None:
    """Any doubles (NaN, inf, subnormal, +-1e308) pack: counts in range, NaN as 0."""
    frame = codec.decode_command(codec.encode_command(1, (0,) * 6, tau, lim))
    for sent, got in zip(tau, frame.torque_nm, strict=True):
        assert p.INT16_MIN * LSB_T <= got <= p.TORQUE_RANGE_NM
        if sent != sent:
            assert got == 0.0
    for sent, got in zip(lim, frame.torque_limit_nm, strict=True):
        assert 0.0 <= got <= p.UINT16_MAX * LSB_T
        if not sent > 0.0:
            assert got == 0.0
        else:
            assert got <= sent + 1e-9  # never a larger limit than asked for


def test_scaling_covers_the_drive_limits_with_margin() -> None:
    cfg = DriveBusConfig()
    assert p.TORQUE_RANGE_NM >= 2 * max(cfg.tau_max_nm)
    assert LSB_T / min(cfg.tau_max_nm) < 2e-4  # < 0.02 % of the smallest limit
    from hapticloud.core.robot import RobotModel

    model = RobotModel.load()
    assert p.VELOCITY_RANGE_RAD_S >= 5 * float(model.v_max.max())
    assert cfg.for_model(model).tau_max_nm == cfg.tau_max_nm  # defaults = the URDF's limits
    span = float((model.q_max - model.q_min).max())
    assert span / LSB_Q < 2**31  # whole joint range, sub-microradian steps


# ----- the DBC ------------------------------------------------------------------------------------
def test_dbc_asset_is_what_the_code_generates(db) -> None:
    assert codec.default_dbc_path().resolve() == DBC_PATH.resolve()
    assert DBC_PATH.read_text() == codec.dbc_text(), (
        "regenerate: python -m hapticloud.hardware.drives dbc assets/can/anyexo_drives.dbc"
    )
    ids = {m.frame_id: m for m in db.messages}
    expected = {p.NMT_ID: p.NMT_DLC, p.SYNC_ID: p.SYNC_DLC, p.COMMAND_ID: p.COMMAND_DLC}
    for node in range(1, 7):
        expected[p.FEEDBACK_BASE_ID + node] = p.FEEDBACK_DLC
        expected[p.EMCY_BASE_ID + node] = p.EMCY_DLC
        expected[p.HEARTBEAT_BASE_ID + node] = p.HEARTBEAT_DLC
    assert {i: m.length for i, m in ids.items()} == expected
    assert all(m.is_fd for m in db.messages)
    assert ids[p.FEEDBACK_BASE_ID + 3].senders == ["Drive3"]


@settings(max_examples=60)
@given(
    cycle=st.integers(0, 2**32 - 1),
    cws=six(words, min_size=6, max_size=6),
    tau=six(st.integers(p.INT16_MIN, p.INT16_MAX), min_size=6, max_size=6),
    lim=six(st.integers(0, p.UINT16_MAX), min_size=6, max_size=6),
)
def test_cantools_decodes_the_command_we_pack(db, cycle, cws, tau, lim) -> None:
    data = codec.encode_command_raw(cycle, cws, tau, lim)
    decoded = db.decode_message(p.COMMAND_ID, data, decode_choices=False)
    assert decoded["CycleCounter"] == cycle
    for i in range(6):
        assert decoded[f"Controlword{i + 1}"] == cws[i]
        assert decoded[f"TargetTorque{i + 1}"] == pytest.approx(tau[i] * LSB_T, abs=1e-9)
        assert decoded[f"TorqueLimit{i + 1}"] == pytest.approx(lim[i] * LSB_T, abs=1e-9)
    # And the other way: cantools packs, struct unpacks.
    again = db.encode_message(p.COMMAND_ID, decoded, scaling=True, padding=True)
    assert codec.decode_command(again)[:2] == (cycle, tuple(cws))


@settings(max_examples=60)
@given(
    node=st.integers(1, 6),
    pos=st.integers(p.INT32_MIN, p.INT32_MAX),
    vel=st.integers(p.INT16_MIN, p.INT16_MAX),
    tau=st.integers(p.INT16_MIN, p.INT16_MAX),
    sw=words,
    sync=st.integers(0, 255),
    cmd=st.integers(0, 255),
)
def test_cantools_decodes_the_feedback_we_pack(db, node, pos, vel, tau, sw, sync, cmd) -> None:
    data = codec.FEEDBACK.pack(pos, vel, tau, sw, sync, cmd)
    d = db.decode_message(p.FEEDBACK_BASE_ID + node, data, decode_choices=False)
    mine = codec.decode_feedback(data)
    assert d[f"Position{node}"] == pytest.approx(mine.position_rad, abs=1e-9)
    assert d[f"Velocity{node}"] == pytest.approx(mine.velocity_rad_s, abs=1e-9)
    assert d[f"Torque{node}"] == pytest.approx(mine.torque_nm, abs=1e-9)
    assert (d[f"Statusword{node}"], d[f"SyncCounter{node}"], d[f"CommandCounter{node}"]) == (
        sw,
        sync,
        cmd,
    )


def test_cantools_decodes_emcy_heartbeat_sync_nmt(db) -> None:
    d = db.decode_message(p.EMCY_BASE_ID + 2, codec.encode_emcy(0x8250, 0x11, 2, 77))
    assert d == {
        "ErrorCode2": "COMMAND_TIMEOUT",
        "ErrorRegister2": 0x11,
        "EmcyNode2": 2,
        "EmcyCycle2": 77,
    }
    hb = db.decode_message(p.HEARTBEAT_BASE_ID + 5, codec.encode_heartbeat(p.NmtState.OPERATIONAL))
    assert hb == {"NmtState5": "OPERATIONAL"}
    assert db.decode_message(p.SYNC_ID, codec.encode_sync(300)) == {"SyncCounter": 300 & 0xFF}
    nmt = db.decode_message(p.NMT_ID, codec.encode_nmt(p.NmtCommand.START, 0))
    assert nmt == {"NmtCommand": "START", "NmtNode": 0}


# ----- CiA 402 ------------------------------------------------------------------------------------
@pytest.mark.parametrize("state", list(DriveState))
def test_statusword_encodes_every_state(state) -> None:
    assert p.state_of(p.statusword_of(state)) is state
    assert p.state_of(p.statusword_of(state, warning=True)) is state
    fault_bit = bool(p.statusword_of(state) & p.Statusword.FAULT)
    assert fault_bit == (state in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE))


def _run(cws: list[int], state: DriveState = DriveState.SWITCH_ON_DISABLED) -> list[DriveState]:
    out, prev = [], 0
    for cw in cws:
        state = p.next_state(state, cw, prev)
        prev = cw
        out.append(state)
    return out


def test_enable_needs_shutdown_switch_on_enable_in_order() -> None:
    assert _run([CW_ENABLE_OPERATION] * 5)[-1] is DriveState.SWITCH_ON_DISABLED
    assert _run([CW_SWITCH_ON] * 5)[-1] is DriveState.SWITCH_ON_DISABLED
    assert _run([CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION]) == [
        DriveState.READY_TO_SWITCH_ON,
        DriveState.SWITCHED_ON,
        DriveState.OPERATION_ENABLED,
    ]
    # READY + "switch on and enable" switches on only; enabling takes one more SYNC.
    assert _run([CW_SHUTDOWN, CW_ENABLE_OPERATION, CW_ENABLE_OPERATION])[1:] == [
        DriveState.SWITCHED_ON,
        DriveState.OPERATION_ENABLED,
    ]
    # Quick stop from enabled brakes and stays there until the voltage is disabled.
    seq = _run([CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE_OPERATION, 0x02, 0x0F, 0x00])
    assert seq[3:] == [
        DriveState.QUICK_STOP_ACTIVE,
        DriveState.QUICK_STOP_ACTIVE,
        DriveState.SWITCH_ON_DISABLED,
    ]


@given(st.lists(words, max_size=40))
def test_operation_enabled_only_ever_entered_from_switched_on_by_enable(cws) -> None:
    state, prev = DriveState.SWITCH_ON_DISABLED, 0
    for cw in cws:
        new = p.next_state(state, cw, prev)
        if new is DriveState.OPERATION_ENABLED and state is not DriveState.OPERATION_ENABLED:
            assert state is DriveState.SWITCHED_ON and (cw & 0x8F) == CW_ENABLE_OPERATION
        state, prev = new, cw


@given(st.lists(words.filter(lambda w: not w & CW_FAULT_RESET), max_size=30))
def test_fault_is_left_only_on_a_fault_reset_edge(cws) -> None:
    assert set(_run(cws, DriveState.FAULT)) <= {DriveState.FAULT}
    assert _run([0, CW_FAULT_RESET], DriveState.FAULT)[-1] is DriveState.SWITCH_ON_DISABLED
    # Holding bit 7 high is not an edge.
    state = p.next_state(DriveState.FAULT, CW_FAULT_RESET, CW_FAULT_RESET)
    assert state is DriveState.FAULT


@pytest.mark.parametrize("start", list(DriveState))
@pytest.mark.parametrize("target", list(DriveTarget))
def test_sequencer_reaches_every_target_or_refuses_to_reset(start, target) -> None:
    state, prev = start, 0
    for _ in range(8):
        cw = p.controlword_towards(state, target, prev)
        state = p.next_state(state, cw, prev)
        prev = cw
    internal = (DriveState.NOT_READY_TO_SWITCH_ON, DriveState.FAULT_REACTION_ACTIVE)
    if start in internal:
        assert state is start  # left only by the drive itself
    elif start is DriveState.FAULT and target is not DriveTarget.FAULT_RESET:
        assert state is DriveState.FAULT  # never an implicit reset
    else:
        assert p.target_reached(state, target)


# ----- bus load -----------------------------------------------------------------------------------
def test_frame_bit_counts() -> None:
    # Classic: 47 + 8n bits; worst-case stuffing floor((34 + 8n - 1) / 4).
    assert schedule.frame_bits(8, fd=False, stuffing="none") == (111, 0)
    assert schedule.frame_bits(8, fd=False) == (135, 0)
    assert schedule.frame_bits(0, fd=False) == (55, 0)
    # FD 12 bytes with BRS: 29 nominal + 1+4+96+4+17+6+1 = 129 data bits without stuffing.
    assert schedule.frame_bits(12, stuffing="none") == (29, 129)
    # 48 bytes: CRC-21 and 7 fixed stuff bits.
    assert schedule.frame_bits(48, stuffing="none") == (29, 1 + 4 + 384 + 4 + 21 + 7 + 1)
    nb, db_ = schedule.frame_bits(48, brs=False, stuffing="none")
    assert (nb, db_) == (29 + 422, 0)
    with pytest.raises(ValueError, match="CAN FD length"):
        schedule.frame_bits(40)
    assert schedule.fd_length(40) == 48


def test_bus_load_matches_the_measured_figures() -> None:
    fd = schedule.bus_load(
        schedule.drive_schedule(DriveBusConfig(), heartbeats=False),
        cycle_rate_hz=800,
        nominal_bitrate=1e6,
        data_bitrate=5e6,
    )
    assert 0.40 < fd.load < 0.50  # "about 46 %"
    table = schedule.load_table()
    classic_split = next(r for r in table if "same content" in r["case"])
    cia = next(r for r in table if "CiA 402" in r["case"])
    assert 130 < classic_split["load_pct_no_stuffing"] < 137  # "134 %"
    assert 155 < cia["load_pct_worst"] < 165  # "160 %"
    live = schedule.config_load(DriveBusConfig())
    assert live.load > fd.load and {r.name for r in live.rows} >= {"command", "heartbeat"}


# ----- docstring examples of the drive package ----------------------------------------------------
@pytest.mark.parametrize(
    "name", ["protocol", "codec", "schedule", "config", "link", "emulator", "faults"]
)
def test_docstring_examples(name: str) -> None:
    module = importlib.import_module(f"hapticloud.hardware.drives.{name}")
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0


# ----- configuration ------------------------------------------------------------------------------
def test_bus_config_validates_and_round_trips() -> None:
    from hapticloud.core.errors import ConfigError
    from hapticloud.hardware.drives import EmulatorConfig, FaultConfig

    cfg = DriveBusConfig()
    assert DriveBusConfig.from_dict(cfg.to_dict()) == cfg
    assert cfg.cycle_period_s == pytest.approx(1.25e-3)
    for cls in (EmulatorConfig, FaultConfig):
        assert cls.from_dict(cls().to_dict()) == cls()
    with pytest.raises(ConfigError, match="tau_max_nm: expected 6"):
        DriveBusConfig(tau_max_nm=(80.0,) * 5)
    with pytest.raises(ConfigError, match=r"tau_max_nm\[0\]"):
        DriveBusConfig(tau_max_nm=(200.0,) * 6)  # beyond the int16 torque field
    with pytest.raises(ConfigError, match="data_bitrate"):
        DriveBusConfig(data_bitrate=500_000)
    with pytest.raises(ConfigError, match="heartbeat_timeout_s"):
        DriveBusConfig(heartbeat_timeout_s=0.005)
    with pytest.raises(ConfigError, match="feedback_timeout_s"):
        DriveBusConfig(feedback_timeout_s=0.001)
    assert "drives.heartbeat_timeout_s" in {i.path for i in DriveBusConfig.params("drives")}


def test_snapshots_pickle_for_other_processes() -> None:
    import pickle

    import can
    from hapticloud.hardware.drives.link import DriveLink

    bus = can.Bus(interface="virtual", channel="drive-test-pickle", protocol=can.CanProtocol.CAN_FD)
    try:
        fb = DriveLink(bus).snapshot()
    finally:
        bus.shutdown()
    again = pickle.loads(pickle.dumps(fb))
    assert again.seq == fb.seq and again.state == fb.state
    np_equal = (again.position_rad == fb.position_rad).all()
    assert np_equal
