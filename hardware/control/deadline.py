"""A periodic loop on absolute deadlines: sleep, then a short spin; misses and jitter counted.

Tick ``k`` is due at ``t_k = t0 + k * period`` (``time.perf_counter``), never "one period after
the previous tick", so lateness does not accumulate. :meth:`DeadlineLoop.wait` sleeps until
``t_k - spin_s`` (the kernel's wake-up is coarse) and then spins on ``perf_counter`` until
``t_k``; :meth:`DeadlineLoop.done` closes the tick's work.

A *miss* is a tick that starts more than one period late, or whose work ends after the next
deadline (an overrun). A tick that falls more than one period behind is not caught up in a burst:
the deadlines it skipped are counted in :attr:`DeadlineStats.skipped` and the loop resumes on the
next future deadline.

:meth:`DeadlineLoop.start` can switch the calling thread to ``SCHED_FIFO`` (permitted for root or
with ``CAP_SYS_NICE``) and falls back to the normal scheduler when the kernel refuses;
:attr:`DeadlineLoop.sched_fifo` and :attr:`DeadlineLoop.sched_note` say what it got. It also
collects, freezes (``gc.freeze``) and disables the garbage collector after start-up: the loop
allocates only short-lived objects, which reference counting frees; :meth:`stop` restores both
the collector and the scheduling policy.
"""

from __future__ import annotations

import gc
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["DeadlineLoop", "DeadlineStats", "lock_memory", "try_sched_fifo"]


#: The nice value a loop takes when SCHED_FIFO is refused (set as is; refused too, it keeps its
#: own): above the app's perception worker (-5) and window (5).
FALLBACK_NICE = -10


def try_sched_fifo(priority: int, fallback_nice: int = FALLBACK_NICE) -> tuple[bool, str]:
    """Switch the calling thread to ``SCHED_FIFO`` at ``priority``; never raises. Refused, it
    takes the nice value ``fallback_nice`` instead (refused too, it keeps its own).

    Returns ``(True, "SCHED_FIFO priority N")`` or ``(False, why)``.
    """
    if not hasattr(os, "sched_setscheduler") or not hasattr(os, "SCHED_FIFO"):
        return False, "SCHED_FIFO not available on this platform"
    try:
        lo = os.sched_get_priority_min(os.SCHED_FIFO)
        hi = os.sched_get_priority_max(os.SCHED_FIFO)
        prio = min(max(int(priority), lo), hi)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
    except (PermissionError, OSError) as exc:
        why = f"SCHED_FIFO refused ({exc.__class__.__name__}: {exc}); normal scheduler"
        try:  # the loop then ahead of the perception worker (nice -5) and the window (nice 5)
            os.setpriority(os.PRIO_PROCESS, 0, fallback_nice)
        except OSError:
            return False, why
        return False, f"{why} at nice {fallback_nice}"
    return True, f"SCHED_FIFO priority {prio}"


@dataclass(frozen=True)
class DeadlineStats:
    """Timing of a :class:`DeadlineLoop` run (microseconds unless named otherwise)."""

    ticks: int
    misses: int
    #: Misses because the work overran the next deadline.
    overruns: int
    #: Misses because the tick started more than one period late.
    late_starts: int
    #: Deadlines skipped after falling more than one period behind.
    skipped: int
    period_us: float
    lateness_us_median: float
    lateness_us_p99: float
    lateness_us_max: float
    work_us_median: float
    work_us_p99: float
    work_us_max: float
    sched_fifo: bool
    sched_note: str

    @property
    def misses_per_10k(self) -> float:
        return 1e4 * self.misses / self.ticks if self.ticks else 0.0

    def as_dict(self) -> dict[str, float | int | bool | str]:
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        out["misses_per_10k"] = self.misses_per_10k
        return out


def _pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if a.size else math.nan


class DeadlineLoop:
    """Absolute-deadline pacing for a periodic loop (one thread; not thread-safe).

    Usage::

        dl = DeadlineLoop(1 / 800)
        dl.start()
        try:
            while running:
                k, t_k = dl.wait()      # returns at t_k (spins the last spin_s)
                ...                     # the tick's work
                dl.done()
        finally:
            dl.stop()
        print(dl.stats())

    Parameters
    ----------
    period_s
        Period (s).
    spin_s
        Sleep until this long before each deadline, then spin.
    fifo_priority
        Try ``SCHED_FIFO`` at this priority in :meth:`start` (``None``: do not try).
    freeze_gc
        ``gc.collect(); gc.freeze(); gc.disable()`` in :meth:`start`, undone in :meth:`stop`.
    capacity
        Per-tick samples kept for the statistics (the first ``capacity`` ticks).
    """

    def __init__(
        self,
        period_s: float,
        *,
        spin_s: float = 200e-6,
        fifo_priority: int | None = None,
        freeze_gc: bool = True,
        capacity: int = 1 << 17,
    ) -> None:
        if not period_s > 0.0:
            raise ValueError(f"period_s = {period_s}: must be > 0")
        if not 0.0 <= spin_s < period_s:
            raise ValueError(f"spin_s = {spin_s}: must be in [0, period_s)")
        self.period_s = float(period_s)
        self.spin_s = float(spin_s)
        self.fifo_priority = fifo_priority
        self.freeze_gc = freeze_gc
        self._late = np.zeros(capacity)
        self._work = np.zeros(capacity)
        self._cap = capacity
        self._t0 = 0.0
        self._k = -1
        self._t_k = 0.0
        self._t_start = 0.0
        self._n = 0
        self._misses = self._overruns = self._late_starts = self._skipped = 0
        self._in_tick = False
        self._started = False
        self._gc_was_enabled = True
        self._old_sched: tuple[int, os.sched_param] | None = None
        self.sched_fifo = False
        self.sched_note = "not requested"

    # ----- life cycle ---------------------------------------------------------------------------
    def start(self, t0: float | None = None) -> None:
        """Scheduler and collector set-up; tick 0 is due at ``t0`` (default: a period from now)."""
        if self.fifo_priority is not None:
            try:
                self._old_sched = (os.sched_getscheduler(0), os.sched_getparam(0))
            except (AttributeError, OSError):
                self._old_sched = None
            self.sched_fifo, self.sched_note = try_sched_fifo(self.fifo_priority)
        if self.freeze_gc:
            self._gc_was_enabled = gc.isenabled()
            gc.collect()
            gc.freeze()
            gc.disable()
        self._t0 = time.perf_counter() + self.period_s if t0 is None else float(t0)
        self._k = -1
        self._started = True

    def stop(self) -> None:
        """Restore the collector and the scheduling policy (idempotent)."""
        if not self._started:
            return
        self._started = False
        if self.freeze_gc:
            gc.unfreeze()
            if self._gc_was_enabled:
                gc.enable()
        if self.sched_fifo and self._old_sched is not None:
            try:
                os.sched_setscheduler(0, *self._old_sched)
            except OSError:
                pass

    @property
    def t0(self) -> float:
        return self._t0

    @property
    def misses(self) -> int:
        """Misses so far (late starts and overruns; see :class:`DeadlineStats`)."""
        return self._misses

    @property
    def tick(self) -> int:
        """Index of the current (last started) tick."""
        return self._k

    # ----- per tick -----------------------------------------------------------------------------
    def wait(self, ahead: Callable[[], object] | None = None) -> tuple[int, float]:
        """Wait for the next deadline; returns ``(k, t_k)`` (``perf_counter`` seconds).

        ``ahead`` is work that can be done before the deadline (reading the frames the drives
        already sent): called once on waking, inside the spin window, only if the deadline is
        still ahead. Its time is the spin's, not the tick's; a call that runs past the deadline
        shows as lateness.
        """
        if self._in_tick:
            self.done()
        period = self.period_s
        k = self._k + 1
        t_k = self._t0 + k * period
        now = time.perf_counter()
        if now - t_k > period:
            # More than one period behind: resume on the next future deadline, count the rest.
            behind = int((now - self._t0) / period) + 1
            self._skipped += behind - k
            k = behind
            t_k = self._t0 + k * period
        wake = t_k - self.spin_s
        if now < wake:
            time.sleep(wake - now)
        if ahead is not None and time.perf_counter() < t_k:
            ahead()
        while True:
            now = time.perf_counter()
            if now >= t_k:
                break
        self._k = k
        self._t_k = t_k
        self._t_start = now
        self._in_tick = True
        return k, t_k

    def done(self) -> None:
        """The current tick's work is over: record its lateness and work time, count a miss."""
        if not self._in_tick:
            return
        self._in_tick = False
        end = time.perf_counter()
        late = self._t_start - self._t_k
        late_start = late > self.period_s
        overrun = end > self._t_k + self.period_s
        if late_start:
            self._late_starts += 1
        if overrun:
            self._overruns += 1
        if late_start or overrun:
            self._misses += 1
        i = self._n
        if i < self._cap:
            self._late[i] = late
            self._work[i] = end - self._t_start
        self._n = i + 1

    # ----- results ------------------------------------------------------------------------------
    def stats(self) -> DeadlineStats:
        n = min(self._n, self._cap)
        late = self._late[:n] * 1e6
        work = self._work[:n] * 1e6
        return DeadlineStats(
            ticks=self._n,
            misses=self._misses,
            overruns=self._overruns,
            late_starts=self._late_starts,
            skipped=self._skipped,
            period_us=self.period_s * 1e6,
            lateness_us_median=_pct(late, 50),
            lateness_us_p99=_pct(late, 99),
            lateness_us_max=float(late.max()) if n else math.nan,
            work_us_median=_pct(work, 50),
            work_us_p99=_pct(work, 99),
            work_us_max=float(work.max()) if n else math.nan,
            sched_fifo=self.sched_fifo,
            sched_note=self.sched_note,
        )


#: glibc ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
#: Heap grown, touched and released (kept) before locking, so that the loop's allocations, the
#: solver's work space in a first contact included, come from pages already resident.
_PREFAULT_HEAP_BYTES = 64 << 20


def lock_memory() -> tuple[bool, str]:
    """Lock the process's memory the real-time Linux way; never raises.

    ``mlockall(MCL_CURRENT | MCL_FUTURE)`` alone made every large ``malloc`` (glibc serves those
    with a fresh ``mmap``) populate and lock its pages on the spot, and ``free`` give them back:
    a controller tick that allocated its solver's work space in a first contact took 10 ms
    (found by ``hapticloud run --hardware``). So first ``mallopt`` turns off ``mmap`` for malloc
    and heap trimming, then a 64 MiB block is touched and freed, which leaves it in the heap,
    resident; then ``mlockall``.
    """
    try:
        import ctypes
        import ctypes.util

        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        tuned = libc.mallopt(_M_TRIM_THRESHOLD, -1) == 1 and libc.mallopt(_M_MMAP_MAX, 0) == 1
        if tuned:
            libc.malloc.restype = ctypes.c_void_p
            libc.free.argtypes = (ctypes.c_void_p,)
            block = libc.malloc(_PREFAULT_HEAP_BYTES)
            if block:
                ctypes.memset(block, 0, _PREFAULT_HEAP_BYTES)
                libc.free(block)
        if libc.mlockall(1 | 2) != 0:
            return False, f"mlockall refused (errno {ctypes.get_errno()}); pages may fault"
    except (OSError, AttributeError) as exc:
        return False, f"mlockall unavailable ({exc})"
    heap = "malloc without mmap or trimming, 64 MiB heap prefaulted; " if tuned else ""
    return True, f"{heap}mlockall(MCL_CURRENT | MCL_FUTURE)"
