"""The control process: the 800 Hz loop on absolute deadlines with drive bus I/O.

- :mod:`.messages`: what crosses its boundaries (commands, replies, the estimate wire form, the
  snapshot, :class:`~.messages.ControlConfig`), one encoding each.
- :mod:`.tick`: :class:`~.tick.ControlTick`, one tick's logic (session, watchdogs, the held
  surface, the haptic tick, the torque by state and reaction), pure and stepped with explicit
  times.
- :mod:`.telemetry`: the per-tick log and the snapshots with their events.
- :mod:`.deadline`: :class:`DeadlineLoop`, absolute-deadline pacing (sleep, then spin), misses and
  jitter, SCHED_FIFO with a clean fallback, the garbage collector frozen.
- :mod:`.child`: the process's body, a deadline loop around the tick (drive link, emulator,
  pipes, shared robot state).
- :mod:`.process`: :class:`ControlProcess`, the parent's handle: commands in and snapshots out
  over pipes that the loop never waits on.
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
