"""The socket-pair CAN FD transport and the shared robot state block."""

from __future__ import annotations

import multiprocessing as mp

import can
import numpy as np
import pytest
from hapticloud.hardware.control.shared_state import RobotStateBlock
from hapticloud.hardware.drives import DriveBusConfig, DriveEmulator, DriveLink, EmulatorConfig
from hapticloud.hardware.drives.protocol import DriveTarget
from hapticloud.hardware.drives.transport import SocketPairBus, socket_pair


@pytest.fixture
def pair():
    a, b = socket_pair()
    master, drives = SocketPairBus(a, channel="m"), SocketPairBus(b, preserve_timestamps=True)
    yield master, drives
    master.shutdown()
    drives.shutdown()


def test_frames_round_trip_with_flags_and_timestamps(pair):
    master, drives = pair
    msg = can.Message(
        arbitration_id=0x181,
        data=bytes(range(48)),
        is_extended_id=False,
        is_fd=True,
        bitrate_switch=True,
        check=False,
    )
    master.send(msg)
    got = drives.recv(1.0)
    assert got is not None
    assert got.arbitration_id == 0x181 and bytes(got.data) == bytes(range(48))
    assert got.is_fd and got.bitrate_switch and not got.is_extended_id and not got.is_error_frame
    # preserve_timestamps sends the message's own stamp (the emulator's release time).
    drives.send(can.Message(timestamp=123.5, arbitration_id=0x80, data=b"\x01", is_fd=True))
    back = master.recv(1.0)
    assert back is not None and back.timestamp == 123.5
    assert master.recv(0.0) is None  # nothing more, never blocks


def test_fast_path_matches_messages(pair):
    master, drives = pair
    master.send_frame(0x200, b"\x05" * 12)
    master.send(can.Message(arbitration_id=0x1, data=b"", is_fd=True, is_error_frame=True))
    frames = drives.read_frames()
    assert frames == [(0x200, b"\x05" * 12, False), (0x1, b"", True)]
    assert drives.read_frames() == []


def test_a_burst_arrives_as_its_frames_in_order_on_both_read_paths(pair):
    master, drives = pair
    # Command + SYNC: two records in one datagram, together shorter than one 64-byte frame's
    # record (a burst must not be mistaken for one frame by its size).
    burst = [(0x200, bytes(range(48))), (0x080, b"\x07")]
    master.send_frames(burst)
    master.send_frame(0x201, b"\x01" * 12)
    master.send_frames([(0x202, b"")] * 3)
    assert drives.read_frames() == [
        (0x200, bytes(range(48)), False),
        (0x080, b"\x07", False),
        (0x201, b"\x01" * 12, False),
        (0x202, b"", False),
        (0x202, b"", False),
        (0x202, b"", False),
    ]
    master.send_frames(burst)
    first = drives.recv(1.0)
    # recv() holds the burst's rest; read_frames() hands it out first.
    master.send_frame(0x203, b"\x02")
    rest = drives.read_frames()
    assert first is not None and (first.arbitration_id, bytes(first.data)) == burst[0]
    assert first.is_fd and first.bitrate_switch
    assert rest == [(0x080, b"\x07", False), (0x203, b"\x02", False)]
    master.send_frames(burst)
    got = [drives.recv(1.0), drives.recv(1.0)]
    assert [(m.arbitration_id, bytes(m.data)) for m in got if m is not None] == burst
    assert drives.recv(0.0) is None


def test_a_truncated_burst_keeps_its_whole_frames(pair):
    import os

    from hapticloud.hardware.drives import transport

    master, drives = pair
    whole = transport._HEADER.pack(1.0, 0x200, 2, 3) + b"abc"
    cut = transport._HEADER.pack(1.0, 0x080, 2, 8) + b"xy"  # says 8 bytes, has 2
    os.write(master.fileno(), whole + cut)
    assert drives.read_frames() == [(0x200, b"abc", False)]
    with pytest.raises(ValueError):
        master.send_frames([])


def test_closed_peer_is_a_bus_error(pair):
    master, drives = pair
    drives.shutdown()
    with pytest.raises(can.CanOperationError):
        master.recv(0.1)


def test_link_and_emulator_cycle_over_the_pair(pair):
    master, drives = pair
    cfg = DriveBusConfig()
    link = DriveLink(master, cfg)
    emu = DriveEmulator(drives, cfg, EmulatorConfig(model_bus_timing=False, drive_response_s=0.0))
    emu.step()
    link.start_nodes()
    emu.step()
    link.run_sequence(DriveTarget.ENABLED, timeout_s=2.0, pump=emu.step)
    for _ in range(20):
        link.send_command(np.full(6, 0.1), link.controlwords(DriveTarget.ENABLED))
        link.send_sync()
        emu.step()
        fb = link.poll_feedback()
        assert fb.complete and fb.all_enabled
    assert link.counters.send_errors == 0


def test_send_cycle_is_command_then_sync_with_the_same_counters(pair):
    from hapticloud.hardware.drives.protocol import COMMAND_ID, SYNC_ID

    master, drives = pair
    cfg = DriveBusConfig()
    # Two links over two pairs, one sending a cycle as a burst, one frame by frame.
    a, b = socket_pair()
    burst_link = DriveLink(master, cfg)
    plain_bus = SocketPairBus(a)
    plain_bus.send_frames = None  # type: ignore[method-assign]  # as a bus without bursts
    plain_link = DriveLink(plain_bus, cfg)
    other_drives = SocketPairBus(b)
    try:
        tau = np.array([1.0, -2.0, 0.5, 0.0, 3.0, -0.25])
        words = (0x0F,) * 6
        sent_burst = burst_link.send_cycle(tau, words)
        sent_plain = plain_link.send_cycle(tau, words)
        np.testing.assert_array_equal(sent_burst, sent_plain)
        frames_burst, frames_plain = drives.read_frames(), other_drives.read_frames()
        assert [f[0] for f in frames_burst] == [COMMAND_ID, SYNC_ID]
        assert frames_burst == frames_plain
        cb, cp = burst_link.counters._asdict(), plain_link.counters._asdict()
        assert cb == cp and cb["commands_sent"] == 1 and cb["syncs_sent"] == 1
        # A failed burst counts both frames as failed, like two failed sends.
        drives.shutdown()
        burst_link.send_cycle(tau, words)
        assert burst_link.counters.send_errors == 2
    finally:
        plain_bus.shutdown()
        other_drives.shutdown()


def _write_in_child(name: str) -> None:
    block = RobotStateBlock.attach(name)
    for k in range(1, 2001):
        v = float(k)
        block.write(v, k, 3, 0, np.full(3, v), np.full(3, v), np.full(6, v), np.full(6, v))
    block.close()


def test_state_block_is_never_torn_across_processes():
    block = RobotStateBlock.create()
    try:
        assert block.read() is None  # before the first write
        proc = mp.get_context("spawn").Process(target=_write_in_child, args=(block.name,))
        proc.start()
        seen = 0
        while proc.is_alive() or seen == 0:
            st = block.read()
            if st is None:
                continue
            seen += 1
            # Every field comes from the same write.
            assert st.t == st.tick
            assert np.all(st.hip_m == st.t) and np.all(st.q_rad == st.t)
            assert np.all(st.qd_rad_s == st.t)
        proc.join(10)
        assert proc.exitcode == 0
        final = block.read()
        assert final is not None and final.tick == 2000 and final.seq == 2000
    finally:
        block.close()
