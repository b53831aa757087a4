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
