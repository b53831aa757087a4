"""Process-wide settings of the numeric libraries, set deliberately.

Thread pools: on 2 cores OpenBLAS's default threads spin after each matrix product and made plain
numpy code several times slower next to other work (measured: p90 80 ms for a 10 ms
deprojection). Every hapticloud process therefore runs BLAS/OpenMP single-threaded unless told
otherwise; the work is parallel across cameras and processes, not inside a matrix product.

Huge pages: numpy asks the kernel for transparent huge pages (``madvise(MADV_HUGEPAGE)``) on every
array of 4 MiB or more, and perception allocates such arrays every frame. While it ran, an 800 Hz
SCHED_FIFO loop stalled 4-5 ms every 10.24 s (the period of the kernel's ``khugepaged`` scan, and
its collapse counter rose each time), and so did the drive emulator, long enough to fault the
drives. With the advice off no huge page was allocated or collapsed and the periodic stalls were
gone (docs/hardware.md, "Timing"). The likely path: the development VMs' kernel runs without
forced preemption (``preempt=none``), so a real-time task woken on a CPU in a long kernel section
waits for it. hapticloud turns the advice off in every process; the arrays live for one frame, so
huge pages bought nothing.
"""

from __future__ import annotations

import os

_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")
#: numpy reads it once, at import (``numpy/__init__.py``).
_HUGEPAGE_VAR = "NUMPY_MADVISE_HUGEPAGE"


def set_environment(threads: int = 1) -> None:
    """Set the thread-count variables and numpy's huge-page advice (off) for this process and
    the processes it starts (effective before numpy is imported; see :func:`numpy_hugepages`)."""
    for var in _VARS:
        os.environ.setdefault(var, str(threads))
    os.environ.setdefault(_HUGEPAGE_VAR, "0")


def numpy_hugepages(enabled: bool = False) -> bool:
    """Set numpy's huge-page advice in this process, numpy already imported; returns the
    previous setting. ``NUMPY_MADVISE_HUGEPAGE=1`` in the environment keeps it on."""
    import numpy as np

    if os.environ.get(_HUGEPAGE_VAR) == "1":
        enabled = True
    try:
        setter = np._core.multiarray._set_madvise_hugepage
    except AttributeError:  # numpy < 2
        setter = np.core.multiarray._set_madvise_hugepage
    return bool(setter(bool(enabled)))


def limit_blas_threads(threads: int = 1) -> object:
    """Limit already-loaded BLAS/OpenMP pools to ``threads``; returns the threadpoolctl handle."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=threads)


def settle_numerics(threads: int = 1) -> object:
    """Both settings in a process whose numpy is already imported (a spawned child, a worker):
    BLAS/OpenMP pools limited to ``threads``, numpy's huge-page advice off. Returns the
    threadpoolctl handle."""
    numpy_hugepages(False)
    return limit_blas_threads(threads)
