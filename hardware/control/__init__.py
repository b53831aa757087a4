"""The control process: the 800 Hz loop on absolute deadlines with drive bus I/O.

- :mod:`.deadline`: :class:`DeadlineLoop`, absolute-deadline pacing (sleep, then spin), misses and
  jitter, SCHED_FIFO with a clean fallback, the garbage collector frozen.
- :mod:`.process`: :class:`ControlProcess`, the loop in its own ``spawn`` process: drive link,
  emulator, haptic tick, session and watchdogs; commands in and snapshots out over pipes that the
  loop never waits on.
- :mod:`.bench`: ``hapticloud bench loop --bus``.
"""

from .deadline import DeadlineLoop, DeadlineStats, try_sched_fifo
from .process import STATE_CODES, ControlProcess, ControlSnapshot

__all__ = [
    "STATE_CODES",
    "ControlProcess",
    "ControlSnapshot",
    "DeadlineLoop",
    "DeadlineStats",
    "try_sched_fifo",
]
