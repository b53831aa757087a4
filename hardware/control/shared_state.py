"""The robot's current state in shared memory: written every tick, read by anyone, nobody waits.

Perception needs the HIP (to crop around it and to cut the robot out of the clouds) at camera
rate, from another process than the 800 Hz loop. A pipe would make the loop write 800 messages a
second that a reader may not drain; instead the loop overwrites one small block of shared memory
(``multiprocessing.shared_memory``) each tick under a sequence lock:

    writer: seq += 1 (odd: writing) ; fields ; seq += 1 (even: consistent)
    reader: s0 = seq ; copy fields ; s1 = seq ; retry unless s0 == s1 and s0 is even

The writer never blocks and never allocates; a reader retries a handful of times at most (a write
takes ~1 µs) and returns ``None`` rather than a torn state. Layout (float64)::

    [0] seq   [1] t (time.monotonic, s)   [2] tick   [3] state code   [4] reaction level
    [5:8] HIP position (world, m)   [8:11] HIP velocity (m/s)   [11:11+n] q (rad)   [..] qd
"""

from __future__ import annotations

import itertools
import os
from multiprocessing import shared_memory
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

__all__ = ["RobotState", "RobotStateBlock"]

_HEADER = 11
_blocks = itertools.count()


class RobotState(NamedTuple):
    """A consistent copy of the block (arrays are fresh copies)."""

    seq: int
    t: float
    tick: int
    state_code: int
    reaction_level: int
    hip_m: NDArray[np.float64]
    hip_velocity_mps: NDArray[np.float64]
    q_rad: NDArray[np.float64]
    qd_rad_s: NDArray[np.float64]


class RobotStateBlock:
    """One shared block: :meth:`create` in the writer's parent, :meth:`attach` elsewhere by name.

    Parameters are for :meth:`create` / :meth:`attach`; the constructor is internal.
    """

    def __init__(self, shm: shared_memory.SharedMemory, n_joints: int, owner: bool) -> None:
        self._shm = shm
        self.n_joints = int(n_joints)
        self._owner = owner
        self._a = np.ndarray((_HEADER + 2 * self.n_joints,), dtype=np.float64, buffer=shm.buf)

    @classmethod
    def create(cls, n_joints: int = 6) -> RobotStateBlock:
        size = 8 * (_HEADER + 2 * int(n_joints))
        name = f"hapticloud-{os.getpid()}-{next(_blocks)}"
        shm = shared_memory.SharedMemory(create=True, size=size, name=name)
        block = cls(shm, n_joints, owner=True)
        block._a[:] = np.nan
        block._a[0] = 0.0
        return block

    @classmethod
    def attach(cls, name: str, n_joints: int = 6) -> RobotStateBlock:
        # Children spawned by the owner's process share its resource tracker, which holds the
        # name once: the owner's unlink releases it.
        shm = shared_memory.SharedMemory(name=name, create=False)
        return cls(shm, n_joints, owner=False)

    @property
    def name(self) -> str:
        return self._shm.name

    def write(
        self,
        t: float,
        tick: int,
        state_code: int,
        reaction_level: int,
        hip_m: NDArray[np.float64],
        hip_velocity_mps: NDArray[np.float64],
        q_rad: NDArray[np.float64],
        qd_rad_s: NDArray[np.float64],
    ) -> None:
        """Overwrite the block (the single writer: the control loop)."""
        a = self._a
        n = self.n_joints
        a[0] += 1.0
        a[1] = t
        a[2] = tick
        a[3] = state_code
        a[4] = reaction_level
        a[5:8] = hip_m
        a[8:11] = hip_velocity_mps
        a[_HEADER : _HEADER + n] = q_rad
        a[_HEADER + n :] = qd_rad_s
        a[0] += 1.0

    def read(self, retries: int = 100) -> RobotState | None:
        """A consistent copy, or ``None`` before the first write or if every retry was torn."""
        a = self._a
        n = self.n_joints
        for _ in range(retries):
            s0 = a[0]
            copy = a.copy()
            if s0 == a[0] == copy[0] and int(s0) % 2 == 0:
                if s0 == 0.0:
                    return None
                return RobotState(
                    int(s0) // 2,
                    float(copy[1]),
                    int(copy[2]),
                    int(copy[3]),
                    int(copy[4]),
                    copy[5:8],
                    copy[8:11],
                    copy[_HEADER : _HEADER + n],
                    copy[_HEADER + n :],
                )
        return None

    def close(self) -> None:
        """Detach; the owner also removes the block."""
        self._a = np.zeros(0)
        try:
            self._shm.close()
        except (BufferError, OSError):
            pass
        if self._owner:
            try:
                self._shm.unlink()
            except FileNotFoundError:
                pass
