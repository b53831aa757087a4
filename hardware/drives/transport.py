"""A python-can bus between two processes: CAN FD frames over a Unix ``SOCK_SEQPACKET`` pair.

Real drives are separate devices: they compute their answers while the master computes its next
command. To emulate that on one machine the drive emulator runs in its own process, and the two
processes need a CAN transport. python-can's ``virtual`` interface is in-process only, and
SocketCAN's ``vcan`` needs a kernel module that containers and CI machines often lack. A
connected ``AF_UNIX``/``SOCK_SEQPACKET`` socket pair keeps frame boundaries, is reliable and
ordered, crosses ``spawn`` (multiprocessing pickles sockets), and costs one system call per frame:
no ``deepcopy`` of each message and no locked queue, which is most of what ``virtual`` costs per
frame (measured in docs/benchmarks.md).

One datagram per frame::

    <d I B B> timestamp (s), arbitration id, flags, data length;  then the data bytes

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
from typing import Any

import can

__all__ = ["SocketPairBus", "socket_pair"]

_HEADER = struct.Struct("<dIBB")
_MAX_DATAGRAM = _HEADER.size + 64
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
        stamp, can_id, flags, length = _HEADER.unpack_from(datagram)
        msg = can.Message(
            timestamp=stamp,
            arbitration_id=can_id,
            is_extended_id=bool(flags & _EXT),
            is_fd=bool(flags & _FD),
            bitrate_switch=bool(flags & _BRS),
            error_state_indicator=bool(flags & _ESI),
            is_remote_frame=bool(flags & _RTR),
            is_error_frame=bool(flags & _ERR),
            data=datagram[_HEADER.size : _HEADER.size + length],
            is_rx=True,
            channel=self.channel_info,
            check=False,
        )
        return msg, False

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

    def read_frames(self, limit: int = 512) -> list[tuple[int, bytes, bool]]:
        """Every frame waiting now, as ``(arbitration id, data, is error frame)``; never blocks.
        Raises ``can.CanOperationError`` if the other end closed."""
        out = []
        fd = self._fd
        unpack = _HEADER.unpack_from
        size = _HEADER.size
        for _ in range(limit):
            try:
                datagram = os.read(fd, _MAX_DATAGRAM)
            except BlockingIOError:
                break
            except OSError as exc:
                raise can.CanOperationError(f"receive failed: {exc}") from exc
            if not datagram:
                raise can.CanOperationError("the other end of the bus closed")
            _, can_id, flags, length = unpack(datagram)
            out.append((can_id, datagram[size : size + length], bool(flags & _ERR)))
        return out

    def fileno(self) -> int:
        return self._fd

    def shutdown(self) -> None:
        super().shutdown()
        try:
            self._sock.close()
        except OSError:
            pass
