"""A python-can bus between two processes: CAN FD frames over a Unix ``SOCK_SEQPACKET`` pair.

Real drives are separate devices: they compute their answers while the master computes its next
command. To emulate that on one machine the drive emulator runs in its own process, and the two
processes need a CAN transport. python-can's ``virtual`` interface is in-process only, and
SocketCAN's ``vcan`` needs a kernel module that containers and CI machines often lack. A
connected ``AF_UNIX``/``SOCK_SEQPACKET`` socket pair keeps frame boundaries, is reliable and
ordered, crosses ``spawn`` (multiprocessing pickles sockets), and costs one system call per frame:
no ``deepcopy`` of each message and no locked queue, which is most of what ``virtual`` costs per
frame (measured in docs/benchmarks.md).

One datagram per frame, or per burst of frames handed over together (:meth:`~SocketPairBus.
send_frames`: the master's command and SYNC of one cycle, as a USB-CAN adapter moves several
frames per transfer and as EtherCAT carries a whole cycle in one frame). A datagram is a sequence
of records, one per frame, in bus order::

    <d I B B> timestamp (s), arbitration id, flags, data length;  then the data bytes

The receiver sees the frames one by one either way (``recv``, :meth:`~SocketPairBus.read_frames`);
a burst saves the sender a system call and the receiver a wake-up.

``flags``: bit 0 extended id, 1 FD, 2 bit-rate switch, 3 error-state indicator, 4 remote frame,
5 error frame. Timestamps are the sender's ``msg.timestamp`` with ``preserve_timestamps=True``
(the emulator's release times), else :func:`time.monotonic` at sending, which is system-wide and
so comparable across the two processes.

Each end is one :class:`SocketPairBus` (a ``can.BusABC``: DriveLink and DriveEmulator take it like
any other bus). :func:`socket_pair` makes the two connected sockets.
"""

from __future__ import annotations

import os
import select
import socket
import struct
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

import can

__all__ = ["MAX_BURST", "SocketPairBus", "socket_pair"]

_HEADER = struct.Struct("<dIBB")
_MAX_RECORD = _HEADER.size + 64
#: Frames in one burst at most (a cycle's command and SYNC are two).
MAX_BURST = 16
_MAX_DATAGRAM = MAX_BURST * _MAX_RECORD
_EXT, _FD, _BRS, _ESI, _RTR, _ERR = 1, 2, 4, 8, 16, 32
#: Socket buffer per direction: several hundred cycles of frames, so that a stalled reader never
#: makes the writer block (sends are non-blocking anyway and count a full buffer as an error).
_BUFFER_BYTES = 1 << 20


def socket_pair() -> tuple[socket.socket, socket.socket]:
    """Two connected ``AF_UNIX``/``SOCK_SEQPACKET`` sockets, non-blocking, with large buffers."""
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for s in (a, b):
        s.setblocking(False)
        for opt in (socket.SO_SNDBUF, socket.SO_RCVBUF):
            try:
                s.setsockopt(socket.SOL_SOCKET, opt, _BUFFER_BYTES)
            except OSError:
                pass
    return a, b


def _records(datagram: bytes) -> list[tuple[float, int, int, bytes]]:
    """The frames of one datagram as ``(timestamp, id, flags, data)``; a truncated tail is
    dropped (a sender that died mid-write), never read past."""
    out = []
    size = _HEADER.size
    unpack = _HEADER.unpack_from
    offset, end = 0, len(datagram)
    while offset + size <= end:
        stamp, can_id, flags, length = unpack(datagram, offset)
        start = offset + size
        if start + length > end:
            break
        out.append((stamp, can_id, flags, datagram[start : start + length]))
        offset = start + length
    return out


class SocketPairBus(can.BusABC):
    """One end of a :func:`socket_pair` as a python-can CAN FD bus.

    Parameters
    ----------
    sock
        A connected ``SOCK_SEQPACKET`` socket (this bus closes it on :meth:`shutdown`).
    preserve_timestamps
        Send ``msg.timestamp`` as is (like the ``virtual`` interface's option); otherwise stamp
        frames with :func:`time.monotonic` when they are sent.
    channel
        A name for logs.
    """

    def __init__(
        self,
        sock: socket.socket,
        *,
        preserve_timestamps: bool = False,
        channel: str = "socketpair",
        **kwargs: Any,
    ) -> None:
        self._sock = sock
        sock.setblocking(False)
        self._fd = sock.fileno()
        self._preserve = preserve_timestamps
        # Frames of a burst not yet returned by recv(), oldest first.
        self._backlog: deque[can.Message] = deque()
        self.channel_info = f"socketpair {channel}"
        super().__init__(channel=channel, **kwargs)
        self._can_protocol = can.CanProtocol.CAN_FD

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        flags = (
            (_EXT if msg.is_extended_id else 0)
            | (_FD if msg.is_fd else 0)
            | (_BRS if msg.bitrate_switch else 0)
            | (_ESI if msg.error_state_indicator else 0)
            | (_RTR if msg.is_remote_frame else 0)
            | (_ERR if msg.is_error_frame else 0)
        )
        data = bytes(msg.data)
        stamp = msg.timestamp if self._preserve else time.monotonic()
        datagram = _HEADER.pack(stamp, msg.arbitration_id, flags, len(data)) + data
        try:
            os.write(self._fd, datagram)
            return
        except BlockingIOError:
            if not timeout:
                raise can.CanOperationError("transmit buffer full") from None
        except OSError as exc:
            raise can.CanOperationError(f"send failed: {exc}") from exc
        # A full buffer with a timeout: wait for room once, then give up.
        if not select.select((), (self._fd,), (), timeout)[1]:
            raise can.CanOperationError("transmit buffer full (timed out)")
        try:
            os.write(self._fd, datagram)
        except OSError as exc:
            raise can.CanOperationError(f"send failed: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._backlog:
            return self._backlog.popleft(), False
        try:
            datagram = os.read(self._fd, _MAX_DATAGRAM)
        except BlockingIOError:
            if timeout is not None and timeout <= 0.0:
                return None, False
            try:
                if not select.select((self._fd,), (), (), timeout)[0]:
                    return None, False
                datagram = os.read(self._fd, _MAX_DATAGRAM)
            except BlockingIOError:
                return None, False
            except (OSError, ValueError) as exc:
                raise can.CanOperationError(f"receive failed: {exc}") from exc
        except OSError as exc:
            raise can.CanOperationError(f"receive failed: {exc}") from exc
        if not datagram:
            # The other end closed: a bus without a peer.
            raise can.CanOperationError("the other end of the bus closed")
        for stamp, can_id, flags, data in _records(datagram):
            self._backlog.append(
                can.Message(
                    timestamp=stamp,
                    arbitration_id=can_id,
                    is_extended_id=bool(flags & _EXT),
                    is_fd=bool(flags & _FD),
                    bitrate_switch=bool(flags & _BRS),
                    error_state_indicator=bool(flags & _ESI),
                    is_remote_frame=bool(flags & _RTR),
                    is_error_frame=bool(flags & _ERR),
                    data=data,
                    is_rx=True,
                    channel=self.channel_info,
                    check=False,
                )
            )
        if not self._backlog:
            raise can.CanOperationError("receive failed: a datagram without a whole frame")
        return self._backlog.popleft(), False

    # ----- the fast path (DriveLink uses it when the bus has it) ------------------------------
    def send_frame(self, can_id: int, data: bytes, fd: bool = True, brs: bool = True) -> None:
        """Send one standard-id data frame without building a ``can.Message`` (the control
        loop's path: ~1 system call). Raises ``can.CanOperationError`` like :meth:`send`."""
        flags = (_FD if fd else 0) | (_BRS if brs else 0)
        try:
            os.write(self._fd, _HEADER.pack(time.monotonic(), can_id, flags, len(data)) + data)
        except BlockingIOError:
            raise can.CanOperationError("transmit buffer full") from None
        except OSError as exc:
            raise can.CanOperationError(f"send failed: {exc}") from exc

    def send_frames(
        self, frames: Sequence[tuple[int, bytes]], fd: bool = True, brs: bool = True
    ) -> None:
        """Send standard-id data frames as one burst (one system call, one wake-up of the
        receiver), in order; at most :data:`MAX_BURST`. Raises ``can.CanOperationError`` like
        :meth:`send`; then none of them was sent."""
        if not 0 < len(frames) <= MAX_BURST:
            raise ValueError(f"frames: {len(frames)} in one burst; expected 1 to {MAX_BURST}")
        flags = (_FD if fd else 0) | (_BRS if brs else 0)
        stamp = time.monotonic()
        pack = _HEADER.pack
        datagram = b"".join(
            [pack(stamp, can_id, flags, len(data)) + data for can_id, data in frames]
        )
        try:
            os.write(self._fd, datagram)
        except BlockingIOError:
            raise can.CanOperationError("transmit buffer full") from None
        except OSError as exc:
            raise can.CanOperationError(f"send failed: {exc}") from exc

    def read_frames(self, limit: int = 512) -> list[tuple[int, bytes, bool]]:
        """Every frame waiting now, as ``(arbitration id, data, is error frame)``; never blocks.
        ``limit`` bounds the datagrams read. Raises ``can.CanOperationError`` if the other end
        closed."""
        out = []
        fd = self._fd
        size = _HEADER.size
        unpack = _HEADER.unpack_from
        while self._backlog:  # left over by recv(): they came first
            msg = self._backlog.popleft()
            out.append((msg.arbitration_id, bytes(msg.data), msg.is_error_frame))
        for _ in range(limit):
            try:
                datagram = os.read(fd, _MAX_DATAGRAM)
            except BlockingIOError:
                break
            except OSError as exc:
                raise can.CanOperationError(f"receive failed: {exc}") from exc
            if not datagram:
                raise can.CanOperationError("the other end of the bus closed")
            if len(datagram) >= size:  # one frame, the common case, parsed inline
                _, can_id, flags, length = unpack(datagram)
                if size + length == len(datagram):
                    out.append((can_id, datagram[size:], bool(flags & _ERR)))
                    continue
            for _, can_id, flags, data in _records(datagram):
                out.append((can_id, data, bool(flags & _ERR)))
        return out

    def fileno(self) -> int:
        return self._fd

    def shutdown(self) -> None:
        super().shutdown()
        try:
            self._sock.close()
        except OSError:
            pass
